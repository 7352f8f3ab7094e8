"""Trajectory anchor calibration: a platform with known poses ranging to fixed anchors."""
