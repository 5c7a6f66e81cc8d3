"""``lidarcal report``: what the report shows, computed from a bag and a calibration."""
