"""Hand-eye calibration: collect views (sim or a real rig), solve, report, write the camera extrinsics."""
