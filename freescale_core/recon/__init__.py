"""3D Gaussian reconstruction: trainer loop, densification, losses, evaluation."""
