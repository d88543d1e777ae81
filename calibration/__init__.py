"""Calibration of the rig cameras (RGB chessboard/ChArUco, e2calib, extrinsics)."""
