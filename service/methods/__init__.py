"""One module per synthesis method (pdm, pose_space, shape_space, ...)."""
