"""Input/output: PointCloud2 bytes, MCAP bags, calibration, configuration and control files."""
