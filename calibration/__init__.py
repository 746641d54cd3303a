"""Hand-eye calibration: collect views, solve, write world_from_camera (not built yet)."""
