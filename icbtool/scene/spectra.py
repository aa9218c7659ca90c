"""Spectra as Mitsuba 3's RGB variants see them: wavelength lists, ``.spd`` files, black bodies.

Mitsuba 3's RGB variants turn every spectrum of a scene file into linear sRGB once, when the file
is loaded; icbtool does the same, with the same rules (``Properties::get_texture`` and
``spectrum_list_to_srgb`` of Mitsuba 3):

* wavelength:value pairs (and ``.spd`` files): the piecewise-linear spectrum is integrated against
  the CIE 1931 2-degree colour matching functions (tabulated every 5 nm from 360 to 830 nm,
  linearly interpolated) with a 1000-point rule over 360..830 nm, nothing counted outside the
  given wavelengths, scaled so that a unit spectrum has luminance 1, then converted XYZ -> linear
  sRGB. A *reflectance* (anything not emitted) is first multiplied by the CIE D65 illuminant
  (normalised to luminance 1), so a flat reflectance stays grey, and the result is clipped to
  [0, 1]; an *emitted* spectrum (radiance, intensity, irradiance) is not weighted by D65 and only
  negative channels are clipped, so a flat emitted spectrum is slightly purple, as in Mitsuba.
* one value ``v`` (``<spectrum value="0.5"/>``): ``(v, v, v)`` for a reflectance; ``v`` times
  the sRGB of XYZ (1, 1, 1) for an emitter (:data:`EQUAL_ENERGY_RGB`).
* a black body (``<spectrum type="blackbody">``, temperature in kelvin): Planck's law in
  W m^-2 sr^-1 nm^-1, integrated as an emitted spectrum over ``wavelength_min..wavelength_max``
  (what Mitsuba's spectral variants render; its RGB variants refuse black bodies).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: Mitsuba's visible range (nm) and integration rule.
CIE_MIN_NM, CIE_MAX_NM, _STEPS = 360.0, 830.0, 1000
#: Luminance of the unit spectrum under the tabulated CIE y-bar (Mitsuba's normalisation).
CIE_Y_INTEGRAL = 106.7502593994140625
#: Luminance of the tabulated D65 illuminant (Mitsuba's normalisation).
D65_Y_INTEGRAL = 98.99741751876255

# CIE 1931 2-degree colour matching functions and the D65 illuminant, 360..830 nm every 5 nm.
_X = (
    0.0001299, 0.0002321, 0.0004149, 0.0007416, 0.001368, 0.002236, 0.004243, 0.00765, 0.01431,
    0.02319, 0.04351, 0.07763, 0.13438, 0.21477, 0.2839, 0.3285, 0.34828, 0.34806, 0.3362, 0.3187,
    0.2908, 0.2511, 0.19536, 0.1421, 0.09564, 0.05795001, 0.03201, 0.0147, 0.0049, 0.0024, 0.0093,
    0.0291, 0.06327, 0.1096, 0.1655, 0.2257499, 0.2904, 0.3597, 0.4334499, 0.5120501, 0.5945,
    0.6784, 0.7621, 0.8425, 0.9163, 0.9786, 1.0263, 1.0567, 1.0622, 1.0456, 1.0026, 0.9384,
    0.8544499, 0.7514, 0.6424, 0.5419, 0.4479, 0.3608, 0.2835, 0.2187, 0.1649, 0.1212, 0.0874,
    0.0636, 0.04677, 0.0329, 0.0227, 0.01584, 0.01135916, 0.008110916, 0.005790346, 0.004109457,
    0.002899327, 0.00204919, 0.001439971, 0.0009999493, 0.0006900786, 0.0004760213, 0.0003323011,
    0.0002348261, 0.0001661505, 0.000117413, 8.307527e-05, 5.870652e-05, 4.150994e-05,
    2.935326e-05, 2.067383e-05, 1.455977e-05, 1.025398e-05, 7.221456e-06, 5.085868e-06,
    3.581652e-06, 2.522525e-06, 1.776509e-06, 1.251141e-06,
)  # fmt: skip
_Y = (
    3.917e-06, 6.965e-06, 1.239e-05, 2.202e-05, 3.9e-05, 6.4e-05, 0.00012, 0.000217, 0.000396,
    0.00064, 0.00121, 0.00218, 0.004, 0.0073, 0.0116, 0.01684, 0.023, 0.0298, 0.038, 0.048, 0.06,
    0.0739, 0.09098, 0.1126, 0.13902, 0.1693, 0.20802, 0.2586, 0.323, 0.4073, 0.503, 0.6082, 0.71,
    0.7932, 0.862, 0.9148501, 0.954, 0.9803, 0.9949501, 1.0, 0.995, 0.9786, 0.952, 0.9154, 0.87,
    0.8163, 0.757, 0.6949, 0.631, 0.5668, 0.503, 0.4412, 0.381, 0.321, 0.265, 0.217, 0.175, 0.1382,
    0.107, 0.0816, 0.061, 0.04458, 0.032, 0.0232, 0.017, 0.01192, 0.00821, 0.005723, 0.004102,
    0.002929, 0.002091, 0.001484, 0.001047, 0.00074, 0.00052, 0.0003611, 0.0002492, 0.0001719,
    0.00012, 8.48e-05, 6e-05, 4.24e-05, 3e-05, 2.12e-05, 1.499e-05, 1.06e-05, 7.4657e-06,
    5.2578e-06, 3.7029e-06, 2.6078e-06, 1.8366e-06, 1.2934e-06, 9.1093e-07, 6.4153e-07, 4.5181e-07,
)  # fmt: skip
_Z = (
    0.0006061, 0.001086, 0.001946, 0.003486, 0.006450001, 0.01054999, 0.02005001, 0.03621,
    0.06785001, 0.1102, 0.2074, 0.3713, 0.6456, 1.0390501, 1.3856, 1.62296, 1.74706, 1.7826,
    1.77211, 1.7441, 1.6692, 1.5281, 1.28764, 1.0419, 0.8129501, 0.6162, 0.46518, 0.3533, 0.272,
    0.2123, 0.1582, 0.1117, 0.07824999, 0.05725001, 0.04216, 0.02984, 0.0203, 0.0134, 0.008749999,
    0.005749999, 0.0039, 0.002749999, 0.0021, 0.0018, 0.001650001, 0.0014, 0.0011, 0.001, 0.0008,
    0.0006, 0.00034, 0.00024, 0.00019, 1e-04, 4.999999e-05, 3e-05, 2e-05, 1e-05, 0.0, 0.0, 0.0,
    0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
    0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
)  # fmt: skip
_D65 = (
    46.6383, 49.3637, 52.0891, 51.032303, 49.9755, 52.3118, 54.6482, 68.7015, 82.7549, 87.1204,
    91.486, 92.4589, 93.4318, 90.057, 86.6823, 95.7736, 104.865, 110.936, 117.008, 117.41, 117.812,
    116.336006, 114.86101, 115.392, 115.923004, 112.367004, 108.811, 109.08201, 109.354, 108.578,
    107.802, 106.296, 104.79, 106.239, 107.689, 106.047005, 104.405, 104.22499, 104.046005,
    102.023, 99.99999, 98.1671, 96.3342, 96.0611, 95.788, 92.2368, 88.6856, 89.3459, 90.0062,
    89.8026, 89.5991, 88.6489, 87.6987, 85.4936, 83.2886, 83.4939, 83.6992, 81.863, 80.0268,
    80.1207, 80.2146, 81.2462, 82.2778, 80.281, 78.2842, 74.0027, 69.7213, 70.6652, 71.6091,
    72.979, 74.349, 67.9765, 61.604, 65.7448, 69.8856, 72.4863, 75.087, 69.3398, 63.592705,
    55.0054, 46.4182, 56.611805, 66.8054, 65.0941, 63.382805, 63.843403, 64.304, 61.8779, 59.4519,
    55.705402, 51.959003, 54.6998, 57.440605, 58.8765, 60.3125,
)  # fmt: skip

_TABLE_NM = np.linspace(CIE_MIN_NM, CIE_MAX_NM, len(_X))
_XYZ_TABLE = np.stack([_X, _Y, _Z], axis=1).astype(np.float64)
_D65_TABLE = np.asarray(_D65, np.float64) / D65_Y_INTEGRAL
#: XYZ -> linear sRGB (D65 white), the matrix Mitsuba uses.
SRGB_FROM_XYZ = np.array(
    [
        [3.240479, -1.537150, -0.498535],
        [-0.969256, 1.875991, 0.041556],
        [0.055648, -0.204043, 1.057311],
    ]
)
#: Linear sRGB of the equal-energy spectrum of value 1 (XYZ = (1, 1, 1)): a one-value emitted
#: spectrum ``v`` is ``v * EQUAL_ENERGY_RGB``.
EQUAL_ENERGY_RGB = SRGB_FROM_XYZ.sum(axis=1)

# Planck's law (the constants Mitsuba's blackbody plugin uses)
_C_LIGHT, _H_PLANCK, _K_BOLTZMANN = 2.99792458e8, 6.62607004e-34, 1.38064852e-23


class SpectrumError(ValueError):
    """A spectrum that cannot be read (the message names the problem, not the file position)."""


def cie_xyz(wavelengths_nm: np.ndarray) -> np.ndarray:
    """(N, 3) CIE 1931 x-bar, y-bar, z-bar at ``wavelengths_nm`` (N,); 0 outside 360..830 nm."""
    w = np.asarray(wavelengths_nm, np.float64)
    out = np.stack([np.interp(w, _TABLE_NM, _XYZ_TABLE[:, k]) for k in range(3)], axis=1)
    out[(w < CIE_MIN_NM) | (w > CIE_MAX_NM)] = 0.0
    return out


def cie_d65(wavelengths_nm: np.ndarray) -> np.ndarray:
    """(N,) the D65 illuminant at ``wavelengths_nm``, normalised to luminance 1."""
    w = np.asarray(wavelengths_nm, np.float64)
    inside = (w >= CIE_MIN_NM) & (w <= CIE_MAX_NM)
    return np.where(inside, np.interp(w, _TABLE_NM, _D65_TABLE), 0.0)


def _grid() -> np.ndarray:
    return CIE_MIN_NM + np.arange(_STEPS) / (_STEPS - 1) * (CIE_MAX_NM - CIE_MIN_NM)


def _integrate(w: np.ndarray, s: np.ndarray, bounded: bool) -> np.ndarray:
    """Linear sRGB of the spectrum ``s`` sampled at grid points ``w`` (Mitsuba's rule)."""
    xyz = (s @ cie_xyz(w)) * (CIE_MAX_NM - CIE_MIN_NM) / (_STEPS * CIE_Y_INTEGRAL)
    rgb = SRGB_FROM_XYZ @ xyz
    return np.clip(rgb, 0.0, 1.0) if bounded else np.maximum(rgb, 0.0)


def spectrum_to_rgb(
    wavelengths_nm: np.ndarray, values: np.ndarray, *, emitter: bool, bounded: bool | None = None
) -> np.ndarray:
    """(3,) linear sRGB of a piecewise-linear spectrum, as Mitsuba 3's RGB variants load it.

    Args:
        wavelengths_nm: (N,) increasing wavelengths, N >= 1.
        values: (N,) the spectrum at them.
        emitter: True for an emitted spectrum (no D65 weighting, unbounded), False for a
            reflectance (D65-weighted, clipped to [0, 1]).
        bounded: clip to [0, 1] (True) or only negatives (False); None: ``not emitter``.
            Mitsuba reads an index of refraction as a D65-weighted unbounded spectrum.

    Returns:
        (3,) float64 linear sRGB; out-of-gamut channels clipped as described above.

    Raises:
        SpectrumError: empty, mismatched, non-finite or non-increasing wavelengths.
    """
    lam = np.asarray(wavelengths_nm, np.float64).ravel()
    val = np.asarray(values, np.float64).ravel()
    if lam.size == 0 or lam.size != val.size:
        raise SpectrumError(f"needs as many wavelengths as values (got {lam.size}, {val.size})")
    if not (np.all(np.isfinite(lam)) and np.all(np.isfinite(val))):
        raise SpectrumError("wavelengths and values must be finite")
    if np.any(np.diff(lam) <= 0):
        raise SpectrumError("wavelengths must be strictly increasing")
    if lam.size == 1:
        return uniform_to_rgb(float(val[0]), emitter=emitter)
    w = _grid()
    w = w[(w >= lam[0]) & (w <= lam[-1])]
    s = np.interp(w, lam, val)
    if not emitter:
        s = s * cie_d65(w)
    return _integrate(w, s, (not emitter) if bounded is None else bounded)


def uniform_to_rgb(value: float, *, emitter: bool) -> np.ndarray:
    """(3,) linear sRGB of the one-value spectrum ``value`` (grey; an emitter's is purplish)."""
    return value * (EQUAL_ENERGY_RGB if emitter else np.ones(3))


def blackbody_radiance(wavelengths_nm: np.ndarray, temperature_k: float) -> np.ndarray:
    """(N,) Planck's spectral radiance (W m^-2 sr^-1 nm^-1) of a black body at the wavelengths."""
    lam = np.asarray(wavelengths_nm, np.float64) * 1e-9
    c0 = 2 * _H_PLANCK * _C_LIGHT**2
    c1 = _H_PLANCK * _C_LIGHT / _K_BOLTZMANN
    with np.errstate(over="ignore"):
        return 1e-9 * c0 / (lam**5 * np.expm1(c1 / (lam * temperature_k)))


def blackbody_to_rgb(
    temperature_k: float, *, min_nm: float = CIE_MIN_NM, max_nm: float = CIE_MAX_NM
) -> np.ndarray:
    """(3,) linear sRGB of a black body's radiance (emitted: no D65, unbounded), as Mitsuba's
    spectral variants render ``<spectrum type="blackbody">``.

    Raises:
        SpectrumError: a temperature <= 0 or an empty wavelength range.
    """
    if not (np.isfinite(temperature_k) and temperature_k > 0):
        raise SpectrumError(f"black body temperature must be > 0 K, got {temperature_k}")
    if not min_nm < max_nm:
        raise SpectrumError(f"wavelength range is empty ({min_nm}..{max_nm} nm)")
    w = _grid()
    s = np.where((w >= min_nm) & (w <= max_nm), blackbody_radiance(w, temperature_k), 0.0)
    return _integrate(w, s, False)


def parse_pairs(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths and values of ``"400:0.1, 500:0.5"``; one value ``"0.5"`` gives no
    wavelengths and that one value.

    Raises:
        SpectrumError: malformed text.
    """
    items = text.replace(",", " ").split()
    if not items:
        raise SpectrumError("empty spectrum")
    try:
        if len(items) == 1 and ":" not in items[0]:
            return np.zeros(0), np.array([float(items[0])])
        pairs = [x.split(":") for x in items]
        if any(len(p) != 2 for p in pairs):
            raise ValueError
        lam, val = np.array(pairs, np.float64).T
    except ValueError:
        raise SpectrumError(f"not 'wavelength:value' pairs or one value: {text[:60]!r}") from None
    return lam, val


def read_spd(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths and values of a ``.spd`` file (lines ``wavelength value``; ``#`` comments).

    Raises:
        SpectrumError: another extension, a line of more or fewer than two numbers, no data.
    """
    p = Path(path)
    if p.suffix.lower() != ".spd":
        raise SpectrumError(f"spectrum files must be .spd (lines 'wavelength value'): {p.name}")
    lam, val = [], []
    for i, line in enumerate(p.read_text().splitlines(), 1):
        text = line.split("#", 1)[0].split()
        if not text:
            continue
        try:
            if len(text) != 2:
                raise ValueError
            a, b = float(text[0]), float(text[1])
        except ValueError:
            raise SpectrumError(f"{p}:{i}: expected 'wavelength value', got {line!r}") from None
        lam.append(a)
        val.append(b)
    if not lam:
        raise SpectrumError(f"{p}: no 'wavelength value' lines")
    return np.array(lam), np.array(val)


__all__ = [
    "CIE_MAX_NM",
    "CIE_MIN_NM",
    "EQUAL_ENERGY_RGB",
    "SRGB_FROM_XYZ",
    "SpectrumError",
    "blackbody_radiance",
    "blackbody_to_rgb",
    "cie_d65",
    "cie_xyz",
    "parse_pairs",
    "read_spd",
    "spectrum_to_rgb",
    "uniform_to_rgb",
]
