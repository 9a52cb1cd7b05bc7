"""Ground simulator: procedural lunar terrain, descent imagery with ground truth, scoring."""
