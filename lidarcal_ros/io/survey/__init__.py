"""Survey files: LAS/LAZ, trajectory files, control points, DSMs, flight plans."""
