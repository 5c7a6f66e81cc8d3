"""The ``correction_flags`` bits of a corrected point (the README's table of topics): why a
derived field is missing or uncertain. Shared by the compiled correction
(:mod:`lidarcal_ros.core.correction_kernels`), the pipeline that fills the field and the
writers that act on it (LAS withholds the points not corrected).
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


__all__ = [
    "FLAG_GRAZING", "FLAG_NOT_CORRECTED", "FLAG_NO_INTENSITY", "FLAG_NO_NORMAL", "FLAG_ROUGH",
]
