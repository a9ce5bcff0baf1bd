"""Data, numpy only: labelled scans from the simulator and from real recordings (see lidar/types.py)."""
