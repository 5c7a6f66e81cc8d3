"""``lidarcal import``: LAS/LAZ flight lines and a trajectory into a bag."""
