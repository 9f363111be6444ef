"""Scenes: cameras + images, Gaussians, PLY, readers, the sample scene."""
