"""The ``correction_flags`` bits of a corrected point: why a derived field is missing or uncertain.

The table: docs/interface.md, "Corrected clouds". LAS output withholds the points not corrected.
"""

#: Geometry not corrected: non-finite input, time not covered by the trajectory, or point
#: not below it. ``x, y, z`` are the delivered ones; range, incidence, scan_angle and
#: reflectance are NaN. (LAS: the point is also *withheld*.)
FLAG_NOT_CORRECTED = 1
#: ``cos(incidence)`` below ``radiometry.min_cos_incidence``: the normal is taken as uncertain
#: and reflectance bounds the incidence term (``radiometry.uncertain_incidence_max_deg``).
FLAG_GRAZING = 2
#: No plane could be fitted around the point (too few neighbours): incidence and
#: reflectance NaN.
FLAG_NO_NORMAL = 4
#: The cloud has no ``intensity`` field: reflectance NaN.
FLAG_NO_INTENSITY = 8
#: The neighbourhood is not planar at the noise level (building edge, vegetation): the
#: normal, hence incidence, is uncertain (computed all the same); reflectance bounds the
#: incidence term (``radiometry.uncertain_incidence_max_deg``).
FLAG_ROUGH = 16
#: A volume return: not the last return of its pulse (``return_number < number_of_returns``:
#: canopy, a branch, a wire; the beam went on past it), so no surface filled the footprint
#: and ``cos(incidence)`` does not apply. No incidence correction (``cos`` taken as 1: the
#: reflectance is that of normal incidence), incidence NaN; the point is left out of the
#: normals' grid, whose planes then follow the last returns (the terrain under a canopy).
FLAG_VOLUME = 32

__all__ = [
    "FLAG_GRAZING", "FLAG_NOT_CORRECTED", "FLAG_NO_INTENSITY", "FLAG_NO_NORMAL", "FLAG_ROUGH",
    "FLAG_VOLUME",
]
