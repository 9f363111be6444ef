"""Cameras, poses and ray casting."""
