"""Data in and out: bags, clouds, survey files, calibration and configuration files, the report."""
