"""Length units of a clip (numpy only): the names, the ``units`` argument, and the two rules
that pick a unit when it is ``"auto"``: a humanoid's stature (:func:`choose_units`, used by
:func:`neuromotor.model.anatomy.analyse`) and, for other skeletons, the rest pose's size
(:func:`auto_scale`, used by :func:`neuromotor.model.bvh.parse_bvh`).
"""

from __future__ import annotations

import math

import numpy as np

from neuromotor.errors import UserError

__all__ = ["UNIT_SCALES", "resolve_units", "auto_scale", "check_stature", "choose_units"]

# Metres per file unit. "cmu" is the CMU database's own unit, 1/0.45 inch.
UNIT_SCALES: dict[str, float] = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "in": 0.0254,
    "cmu": 0.0254 / 0.45,
    "ft": 0.3048,
    "dm": 0.1,
}
_AUTO_UNITS: tuple[float, ...] = (1.0, 0.01, 0.001)  # m, cm, mm, in this order (ties -> larger unit)
_AUTO_TARGET_SIZE_M = 1.8

_PLAUSIBLE_M = (1.3, 2.2)
_TYPICAL_M = 1.70
_FALLBACK_M = 1.75


def resolve_units(units: str | float) -> float | None:
    """Metres per file unit, or None for 'auto'. UserError naming ``units`` if invalid."""
    if isinstance(units, str):
        key = units.strip().lower()
        if key == "auto":
            return None
        if key in UNIT_SCALES:
            return UNIT_SCALES[key]
    elif isinstance(units, (int, float, np.integer, np.floating)) and not isinstance(units, (bool, np.bool_)):
        value = float(units)
        if math.isfinite(value) and value > 0:
            return value
    raise UserError(
        f"units must be 'auto', one of {', '.join(UNIT_SCALES)} or a positive number of "
        f"metres per file unit, got {units!r}"
    )


def auto_scale(points: np.ndarray) -> float:
    """Metres per file unit of a skeleton that is not humanoid, from its rest-pose joint and End
    Site ``points`` (N, 3) in file units: of m, cm and mm, the one whose bounding-box diagonal is
    nearest 1.8 m in log ratio; metres for a skeleton of zero size."""
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    if not (math.isfinite(size) and size > 0):
        return 1.0
    return min(_AUTO_UNITS, key=lambda s: abs(math.log(size * s / _AUTO_TARGET_SIZE_M)))


def check_stature(stature: float | None) -> float | None:
    if stature is not None:
        stature = float(stature)
        if not (math.isfinite(stature) and stature > 0):
            raise UserError(f"stature must be a positive number of metres, got {stature!r}")
    return stature


def choose_units(
    height_raw: float, fixed: float | None, stature: float | None, warnings: list[str]
) -> tuple[float, str, float]:
    """(metres per file unit, units name, stature in metres) of a body ``height_raw`` file units
    tall: the ``fixed`` scale, else the given ``stature``, else the unit of :data:`UNIT_SCALES`
    giving the most typical adult, else scaled to 1.75 m with a warning."""
    if fixed is not None:
        name = next((k for k, v in UNIT_SCALES.items() if v == fixed), "given")
        return fixed, name, stature if stature is not None else height_raw * fixed
    if stature is not None:
        return stature / height_raw, "given", stature
    best = None
    for name, value in UNIT_SCALES.items():
        h = height_raw * value
        if _PLAUSIBLE_M[0] <= h <= _PLAUSIBLE_M[1]:
            d = abs(math.log(h / _TYPICAL_M))
            if best is None or d < best[0]:
                best = (d, name, value)
    if best is not None:
        return best[2], best[1], height_raw * best[2]
    scale = _FALLBACK_M / height_raw
    warnings.append(
        f"no unit among {', '.join(UNIT_SCALES)} gives a plausible stature "
        f"({_PLAUSIBLE_M[0]}-{_PLAUSIBLE_M[1]} m) for a body {height_raw:.4g} file units tall: "
        f"scaled to {_FALLBACK_M} m ({scale:.4g} m per file unit)"
    )
    return scale, "scaled", _FALLBACK_M
