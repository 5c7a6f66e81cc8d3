"""Radiometric correction: recorded intensity to reflectance (docs/method.md section 8).

Range in metres, angles in radians, the extinction coefficient per metre; vectorised over points,
pure numpy. What the ``reflectance`` field holds: docs/correction.md, "The reflectance".
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarcal_ros.errors import ConfigError

#: Standard air: temperature (K) and pressure (kPa) of Kim's relation and the Rayleigh term.
T0_K = 288.15
P0_KPA = 101.325
#: Rayleigh (molecular) extinction at 550 nm, standard air, per km (Bucholtz 1995).
RAYLEIGH_550_PER_KM = 0.01162


class PowerModel(enum.StrEnum):
    """How the transmitted power varies (``radiometry.power_model``)."""

    #: The same power on every pulse.
    CONSTANT = "constant"
    #: Constant mean power: the pulse energy falls as the repetition frequency rises.
    PULSE_RATE = "pulse_rate"


#: Power models accepted in the flight configuration (``radiometry.power_model``).
POWER_MODELS = tuple(PowerModel)


def parse_power_model(value: str) -> PowerModel:
    """``radiometry.power_model`` as a :class:`PowerModel`.

    Raises
    ------
    ConfigError
        Not one of the models.
    """
    try:
        return PowerModel(value)
    except ValueError:
        raise ConfigError(f"radiometry.power_model: '{value}' is not one of "
                          f"{', '.join(POWER_MODELS)}") from None


def kim_q(visibility_km: float) -> float:
    """Size-distribution exponent ``q`` of Kim et al. (2001) for a visibility in km."""
    v = float(visibility_km)
    if v > 50.0:
        return 1.6
    if v > 6.0:
        return 1.3
    if v > 1.0:
        return 0.16 * v + 0.34
    if v > 0.5:
        return v - 0.5
    return 0.0


def atmospheric_alpha(visibility_km: float = 48.3, wavelength_nm: float = 1064.0) -> float:
    """Extinction coefficient per metre, Kim et al. (2001), at standard air density.

    ``alpha = 3.912 / V * (lambda / 550 nm)^-q`` per km, ``q = 1.6`` (V > 50 km), ``1.3``
    (6 < V <= 50), ``0.16 V + 0.34`` (1 < V <= 6), ``V - 0.5`` (0.5 < V <= 1), else 0.

    Parameters
    ----------
    visibility_km : float
        Meteorological visibility, km.
    wavelength_nm : float
        Laser wavelength, nm.

    Returns
    -------
    float
        Extinction coefficient, 1/m.

    Raises
    ------
    ConfigError
        Non-positive visibility or wavelength.
    """
    v = float(visibility_km)
    if not v > 0:
        raise ConfigError(f"visibility_km must be positive, got {visibility_km}")
    if not float(wavelength_nm) > 0:
        raise ConfigError(f"wavelength_nm must be positive, got {wavelength_nm}")
    per_km = 3.912 / v * (float(wavelength_nm) / 550.0) ** (-kim_q(v))
    return per_km / 1000.0


def rayleigh_alpha(
    wavelength_nm: float, temperature_c: float = 15.0, pressure_kpa: float = P0_KPA
) -> float:
    """Molecular (Rayleigh) extinction per metre at a temperature and pressure.

    ``sigma_R = 0.01162 km^-1 (550 nm / lambda)^4 (P / P_0) (T_0 / T)``.

    Parameters
    ----------
    wavelength_nm : float
        nm.
    temperature_c : float
        Air temperature, deg C.
    pressure_kpa : float
        Air pressure, kPa.

    Returns
    -------
    float
        1/m.
    """
    t_k = float(temperature_c) + 273.15
    if not t_k > 0 or not float(pressure_kpa) > 0 or not float(wavelength_nm) > 0:
        raise ConfigError(
            f"rayleigh_alpha: need positive wavelength, absolute temperature and pressure, got "
            f"{wavelength_nm} nm, {temperature_c} C, {pressure_kpa} kPa"
        )
    density = (float(pressure_kpa) / P0_KPA) * (T0_K / t_k)
    return RAYLEIGH_550_PER_KM * (550.0 / float(wavelength_nm)) ** 4 * density / 1000.0


def extinction_coefficient(
    visibility_km: float,
    wavelength_nm: float,
    temperature_c: float = 15.0,
    pressure_kpa: float = P0_KPA,
) -> float:
    """The day's extinction coefficient per metre (docs/method.md section 8).

    Kim's coefficient at standard air, with its molecular part rescaled to the day's air
    density: ``alpha_Kim(V, lambda) + sigma_R(lambda, T, P) - sigma_R(lambda, 15 C, 101.325 kPa)``
    (never below 0).
    """
    alpha = atmospheric_alpha(visibility_km, wavelength_nm)
    alpha += rayleigh_alpha(wavelength_nm, temperature_c, pressure_kpa)
    alpha -= rayleigh_alpha(wavelength_nm)
    return max(alpha, 0.0)


def two_way_transmittance(range_m: np.ndarray, alpha_per_m: float) -> np.ndarray:
    """``eta_atm(r) = exp(-2 alpha r)``: two-way transmittance over ``range_m`` metres."""
    return np.exp(-2.0 * alpha_per_m * np.asarray(range_m, dtype=np.float64))


def power_ratio(
    model: PowerModel | str, pulse_rate_hz: float, reference_pulse_rate_hz: float
) -> float:
    """Transmitted-power normalisation ``P_ref / P_t``.

    ``constant``: 1. ``pulse_rate``: the pulse energy of a diode-pumped laser falls as the
    repetition frequency rises (constant mean power), ``P_t ~ 1 / PRF``, so
    ``P_ref / P_t = PRF / PRF_ref``.

    Raises
    ------
    ConfigError
        Unknown model or non-positive rate.
    """
    if parse_power_model(model) is PowerModel.CONSTANT:
        return 1.0
    if not (pulse_rate_hz > 0 and reference_pulse_rate_hz > 0):
        raise ConfigError(
            f"pulse rates must be positive, got {pulse_rate_hz} and {reference_pulse_rate_hz}"
        )
    return float(pulse_rate_hz) / float(reference_pulse_rate_hz)


def volume_returns(return_number: np.ndarray | None,
                   number_of_returns: np.ndarray | None) -> np.ndarray | None:
    """The volume returns of a cloud (docs/method.md section 8): not the last return of their pulse.

    Parameters
    ----------
    return_number, number_of_returns : (n,) int or None
        1-based return of each point and returns of its pulse (LAS convention; 0 where the
        sensor did not say).

    Returns
    -------
    (n,) bool or None
        ``1 <= return_number < number_of_returns``; None when either column is missing or no
        point is a volume return (the correction then treats every point as a surface).
    """
    if return_number is None or number_of_returns is None:
        return None
    rn = np.asarray(return_number)
    volume = (rn >= 1) & (rn < np.asarray(number_of_returns))
    return volume if volume.any() else None


def cos_incidence(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """``|n . l|`` per point: cosine of the incidence angle.

    Parameters
    ----------
    normals : (n, 3) float
        Unit surface normals, map frame (either orientation).
    directions : (n, 3) float
        Unit laser directions (sensor to point), map frame.

    Returns
    -------
    (n,) float64
        In [0, 1]; NaN where a normal is NaN.
    """
    d = np.einsum("ij,ij->i", np.asarray(normals, dtype=np.float64),
                  np.asarray(directions, dtype=np.float64))
    return np.minimum(np.abs(d), 1.0)


@dataclass(frozen=True)
class RadiometricModel:
    """Parameters of the radiometric correction, from the flight configuration.

    Attributes
    ----------
    wavelength_nm : float
        Laser wavelength, nm (``sensor.wavelength_nm``).
    visibility_km, temperature_c, pressure_kpa : float
        Atmosphere of the day (``atmosphere.*``): km, deg C, kPa.
    reference_range_m : float
        Range the reflectance is normalised to, m (``radiometry.reference_range_m``).
    calibration_constant : float
        ``C`` of docs/method.md section 8: the intensity of a Lambertian target of reflectance 1
        at ``reference_range_m``, normal incidence, clear air and reference power
        (``radiometry.calibration_constant``, intensity units); 0 when not known (the
        reflectance is then relative, in intensity units).
    power_model : PowerModel
        ``constant`` or ``pulse_rate`` (``radiometry.power_model``).
    pulse_rate_hz, reference_pulse_rate_hz : float
        Pulse repetition frequency of the mission and of the reference power, Hz.
    min_cos_incidence : float
        Clamp of ``cos(theta)``; points below it are flagged grazing
        (``radiometry.min_cos_incidence``).
    uncertain_incidence_max_deg : float
        Bound of the incidence term (deg) for points whose normal is uncertain
        (``radiometry.uncertain_incidence_max_deg``): there a wrong normal, not the surface,
        is the likely cause of a steep incidence, and dividing by its cosine would turn one
        bad neighbourhood into an outlier ten times too bright.
    """

    wavelength_nm: float = 1064.0
    visibility_km: float = 48.3
    temperature_c: float = 29.8
    pressure_kpa: float = 101.81
    reference_range_m: float = 1000.0
    calibration_constant: float = 0.0
    power_model: PowerModel = PowerModel.CONSTANT
    pulse_rate_hz: float = 70000.0
    reference_pulse_rate_hz: float = 70000.0
    min_cos_incidence: float = 0.1
    uncertain_incidence_max_deg: float = 60.0

    def __post_init__(self) -> None:
        if not self.reference_range_m > 0:
            raise ConfigError(
                f"radiometry.reference_range_m must be positive, got {self.reference_range_m}"
            )
        if not (math.isfinite(self.calibration_constant) and self.calibration_constant >= 0):
            raise ConfigError("radiometry.calibration_constant must be 0 (not known) or "
                              f"positive, got {self.calibration_constant}")
        if not 0.0 < self.min_cos_incidence <= 1.0:
            raise ConfigError(
                f"radiometry.min_cos_incidence must be in (0, 1], got {self.min_cos_incidence}"
            )
        if not 0.0 <= self.uncertain_incidence_max_deg < 90.0:
            raise ConfigError("radiometry.uncertain_incidence_max_deg must be in [0, 90) deg, "
                              f"got {self.uncertain_incidence_max_deg}")
        power_ratio(self.power_model, self.pulse_rate_hz, self.reference_pulse_rate_hz)
        extinction_coefficient(self.visibility_km, self.wavelength_nm, self.temperature_c,
                               self.pressure_kpa)

    @classmethod
    def from_config(cls, config: Any) -> RadiometricModel:
        """From a :class:`~lidarcal_ros.core.config.FlightConfig` (or any ``name -> value``
        mapping with the dotted names of the schema)."""
        return cls(
            wavelength_nm=float(config["sensor.wavelength_nm"]),
            visibility_km=float(config["atmosphere.visibility_km"]),
            temperature_c=float(config["atmosphere.temperature_c"]),
            pressure_kpa=float(config["atmosphere.pressure_kpa"]),
            reference_range_m=float(config["radiometry.reference_range_m"]),
            calibration_constant=float(config["radiometry.calibration_constant"]),
            power_model=parse_power_model(str(config["radiometry.power_model"])),
            pulse_rate_hz=float(config["sensor.pulse_rate_hz"]),
            reference_pulse_rate_hz=float(config["radiometry.reference_pulse_rate_hz"]),
            min_cos_incidence=float(config["radiometry.min_cos_incidence"]),
            uncertain_incidence_max_deg=float(config["radiometry.uncertain_incidence_max_deg"]),
        )

    @property
    def alpha_per_m(self) -> float:
        """The day's extinction coefficient, 1/m (:func:`extinction_coefficient`)."""
        return extinction_coefficient(self.visibility_km, self.wavelength_nm,
                                      self.temperature_c, self.pressure_kpa)

    @property
    def power_factor(self) -> float:
        """``P_ref / P_t`` (:func:`power_ratio`)."""
        return power_ratio(self.power_model, self.pulse_rate_hz, self.reference_pulse_rate_hz)

    @property
    def absolute(self) -> bool:
        """Whether the reflectance is absolute (a calibration constant is known)."""
        return self.calibration_constant > 0

    @property
    def unit(self) -> str:
        """Unit of the reflectance: ``1`` (absolute) or ``intensity units`` (relative)."""
        return "1" if self.absolute else "intensity units"

    @property
    def meaning(self) -> str:
        """What the reflectance is, in one sentence (for reports and logs)."""
        reference = (f"{self.reference_range_m:g} m range, normal incidence, clear air and "
                     "reference power")
        if self.absolute:
            return (f"Lambertian reflectance (dimensionless, 0-1 for natural surfaces): the "
                    f"intensity normalised to {reference}, divided by the calibration "
                    f"constant {self.calibration_constant:.6g} (the intensity of a "
                    "reflectance-1 target there).")
        return (f"relative reflectance in intensity units: the intensity the sensor would "
                f"record from the same surface at {reference} (no calibration constant: "
                "proportional to the Lambertian reflectance by one unknown factor).")

    @property
    def las_description(self) -> str:
        """The reflectance's meaning in the 32 characters of a LAS extra-bytes description."""
        if self.absolute:
            return "Lambertian reflectance, 0-1"
        return f"I at {self.reference_range_m:g} m, 0 deg incidence"[:32]

    @property
    def incidence_rule(self) -> str:
        """The incidence rule of the reflectance in one line (docs/method.md section 8,
        "Volume returns"), for logs and diagnostics."""
        return (f"cos of the surface normal's incidence, at least {self.min_cos_incidence:g} "
                f"(grazing, flagged), where the normal is rough or grazing at most "
                f"{self.uncertain_incidence_max_deg:g} deg; none (cos 1) for volume returns, "
                "not the last of their pulse (canopy)")

    def with_constant(self, calibration_constant: float) -> RadiometricModel:
        """The same model with another calibration constant (intensity units; 0: none)."""
        return dataclasses.replace(self, calibration_constant=float(calibration_constant))

    def reflectance(
        self,
        intensity: np.ndarray,
        range_m: np.ndarray,
        cos_theta: np.ndarray,
        *,
        uncertain: np.ndarray | None = None,
        volume: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Reflectance of each point (docs/method.md section 8) and its grazing flag.

        Parameters
        ----------
        intensity : (n,) float
            Recorded intensity (any unit).
        range_m : (n,) float
            Firing point to point, metres.
        cos_theta : (n,) float
            ``|n . l|``, cosine of the incidence angle (NaN where unknown).
        uncertain : (n,) bool, keyword-only, optional
            The normal is uncertain (rough neighbourhood): the cosine used is at least
            ``cos(uncertain_incidence_max_deg)``. Points beyond the grazing clamp are
            uncertain too.
        volume : (n,) bool, keyword-only, optional
            Volume returns (:func:`volume_returns`): no incidence correction, ``cos`` taken
            as 1 whatever ``cos_theta`` says (NaN included); never grazing.

        Returns
        -------
        reflectance : (n,) float32
            ``I (r / r_ref)^2 / max(cos theta, c) / exp(-2 alpha r) * P_ref / P_t / C`` with
            ``c = cos(uncertain_incidence_max_deg)`` for uncertain and grazing points, else
            ``c_min``, 1 for volume returns, and ``C`` the calibration constant (1 when not
            known); NaN where an input is NaN. Dimensionless with a calibration constant, else
            in the unit of the intensity.
        grazing : (n,) bool
            ``cos theta < c_min`` (volume returns excepted): the clamped value was used;
            never divided by a cosine below ``c_min``.
        """
        # float32 throughout (the result's type; relative precision 1e-7).
        c_min, c_doubt, scale, two_alpha = self.kernel_constants()
        r = np.asarray(range_m, dtype=np.float32)
        cos_t = np.asarray(cos_theta, dtype=np.float32)
        grazing = cos_t < c_min  # False for NaN
        cos_eff = np.maximum(cos_t, c_min)  # NaN stays NaN
        doubtful = grazing if uncertain is None else (grazing | np.asarray(uncertain, bool))
        if doubtful.any():
            cos_eff[doubtful] = np.maximum(cos_eff[doubtful], c_doubt)
        if volume is not None:
            vol = np.asarray(volume, dtype=bool)
            cos_eff[vol] = np.float32(1.0)
            grazing &= ~vol
        gain = np.exp(two_alpha * r)
        gain *= r
        gain *= r
        gain *= scale
        gain /= cos_eff
        gain *= np.asarray(intensity, dtype=np.float32)
        return gain, grazing

    def kernel_constants(self) -> tuple[np.float32, np.float32, np.float32, np.float32]:
        """The float32 constants of :meth:`reflectance` (and of the compiled correction,
        :func:`lidarcal_ros.core.georeferencing.correction_kernels.correct_returns`, which repeats
        its arithmetic).

        Returns
        -------
        c_min : float32
            ``min_cos_incidence``.
        c_doubt : float32
            ``cos(uncertain_incidence_max_deg)``, at least ``c_min``.
        scale : float32
            ``P_ref / P_t / r_ref^2 / C``, 1/m^2 per intensity unit (``C`` = 1 when the
            calibration constant is not known).
        two_alpha : float32
            ``2 alpha``, 1/m (two-way extinction).
        """
        c_doubt = max(math.cos(math.radians(self.uncertain_incidence_max_deg)),
                      self.min_cos_incidence)
        return (np.float32(self.min_cos_incidence), np.float32(c_doubt),
                np.float32(self.power_factor / (self.reference_range_m
                                                * self.reference_range_m)
                           / (self.calibration_constant if self.absolute else 1.0)),
                np.float32(2.0 * self.alpha_per_m))


def describe_alpha(model: RadiometricModel) -> str:
    """One line on the atmosphere used (for logs and reports)."""
    a = model.alpha_per_m
    return (f"alpha {a * 1000:.4f}/km at {model.wavelength_nm:g} nm (visibility "
            f"{model.visibility_km:g} km, q {kim_q(model.visibility_km):.2f}, "
            f"{model.temperature_c:g} C, {model.pressure_kpa:g} kPa); two-way transmittance "
            f"{math.exp(-2 * a * model.reference_range_m):.4f} at {model.reference_range_m:g} m")


def constant_from_target(relative: np.ndarray, known_reflectance: float) -> float:
    """The calibration constant that makes a reference target read its known reflectance.

    Parameters
    ----------
    relative : (n,) float
        Relative reflectance (calibration constant 1: intensity units) of the target's
        points whose incidence and normal are trusted.
    known_reflectance : float
        The target's Lambertian reflectance, in (0, 1.5].

    Returns
    -------
    float
        ``median(relative) / known_reflectance``, intensity units (the median: a few points
        of another surface on the target's edge do not move it).

    Raises
    ------
    ConfigError
        No finite positive value, or a known reflectance out of range.
    """
    if not 0.0 < float(known_reflectance) <= 1.5:
        raise ConfigError("radiometry.reference_target_reflectance must be in (0, 1.5], got "
                          f"{known_reflectance}")
    values = np.asarray(relative, dtype=np.float64)
    values = values[np.isfinite(values) & (values > 0)]
    if not values.size:
        raise ConfigError("radiometry.reference_target: no point of the target has a "
                          "reflectance (none inside it, or all rough, grazing or without "
                          "intensity)")
    return float(np.median(values)) / float(known_reflectance)


__all__ = [
    "P0_KPA",
    "POWER_MODELS",
    "RAYLEIGH_550_PER_KM",
    "T0_K",
    "PowerModel",
    "RadiometricModel",
    "atmospheric_alpha",
    "constant_from_target",
    "cos_incidence",
    "describe_alpha",
    "extinction_coefficient",
    "kim_q",
    "parse_power_model",
    "power_ratio",
    "rayleigh_alpha",
    "two_way_transmittance",
    "volume_returns",
]
