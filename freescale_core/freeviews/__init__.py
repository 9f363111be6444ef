"""METHOD stages 7-10: render, quality filter, pose and image rectification, references."""
