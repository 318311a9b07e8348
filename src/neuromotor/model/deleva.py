"""Anthropometric segment parameters: de Leva (1996), Table 4, and the stature proportions used
to size missing geometry.

Source: P. de Leva, "Adjustments to Zatsiorsky-Seluyanov's segment inertia parameters",
Journal of Biomechanics 29(9):1223-1230, 1996, Table 4 (segment masses in percent of body
mass; centre-of-mass positions and radii of gyration in percent of the segment length, the
length measured between the endpoints named in the table). ``"average"`` is the mean of the
male and female columns. Published measurements (facts), typed in from the paper.

Segments and their endpoints (proximal -> distal, the direction the COM position is measured):

============  =============================================  ==================
segment       endpoints                                      our joint
============  =============================================  ==================
head          vertex -> cervicale (C7); includes the neck    neck .. skull
trunk         cervicale -> mid-hip (hip joint centres)       pelvis .. chest
upper_arm     shoulder joint centre -> elbow joint centre    shoulder
forearm       elbow joint centre -> wrist joint centre       elbow
hand          wrist joint centre -> 3rd metacarpale          wrist
thigh         hip joint centre -> knee joint centre          hip
shank         knee joint centre -> lateral malleolus         knee
foot          heel -> tip of the longest toe                 ankle
============  =============================================  ==================
"""

from __future__ import annotations

import dataclasses

from neuromotor.errors import UserError

__all__ = ["SegmentParameters", "SEX", "segment_parameters", "mass_fractions", "LENGTH_OF_STATURE", "DEFAULT_BMI"]

SEX = ("male", "female", "average")

# Body-mass index used when neither body_mass nor a weight is given (kg / m^2): a typical adult.
DEFAULT_BMI = 22.0


@dataclasses.dataclass(frozen=True)
class SegmentParameters:
    """One segment of de Leva's Table 4 (fractions, not percent)."""

    mass: float  # of body mass
    com: float  # of the segment length, from the proximal endpoint (see the module table)
    r_sagittal: float  # radii of gyration about the COM, of the segment length
    r_transverse: float
    r_longitudinal: float


# Per segment, the male and the female row of (mass %, COM %, r_sag %, r_trans %, r_long %). The
# head's and trunk's COM positions are measured from the vertex and from the cervicale (their
# proximal endpoints in the table).
_TABLE4 = {  # segment: (male, female)
    "head": ((6.94, 59.76, 36.2, 37.6, 31.2), (6.68, 58.94, 33.0, 35.9, 31.8)),
    "trunk": ((43.46, 44.86, 37.2, 34.7, 19.1), (42.57, 41.51, 35.7, 33.9, 17.1)),
    "upper_arm": ((2.71, 57.72, 28.5, 26.9, 15.8), (2.55, 57.54, 27.8, 26.0, 14.8)),
    "forearm": ((1.62, 45.74, 27.6, 26.5, 12.1), (1.38, 45.59, 26.1, 25.7, 9.4)),
    "hand": ((0.61, 79.0, 62.8, 51.3, 40.1), (0.56, 74.74, 53.1, 45.4, 33.5)),
    "thigh": ((14.16, 40.95, 32.9, 32.9, 14.9), (14.78, 36.12, 36.9, 36.4, 16.2)),
    "shank": ((4.33, 44.59, 25.5, 24.9, 10.3), (4.81, 44.16, 27.1, 26.7, 9.3)),
    "foot": ((1.37, 44.15, 25.7, 24.5, 12.4), (1.29, 40.14, 29.9, 27.9, 13.9)),
}
_SEX_COLUMN = {"male": 0, "female": 1}

# Segment lengths as fractions of stature, from de Leva's Table 1 mean lengths over his mean
# statures (1741 mm male, 1735 mm female), averaged over the sexes; ``hand_full`` (wrist to the
# tip of the middle finger) and ``ankle_height`` (sole to the lateral malleolus) from the
# classic Drillis & Contini proportions (0.108 H and 0.039 H), and the breadths used to shape
# the polyhedra from common anthropometric surveys (rounded; they only set the look: masses
# come from Table 4).
LENGTH_OF_STATURE = {
    "head": 0.140,  # vertex -> cervicale
    "trunk": 0.350,  # cervicale -> mid-hip
    "upper_arm": 0.160,
    "forearm": 0.153,
    "hand": 0.047,  # wrist -> 3rd metacarpale
    "hand_full": 0.108,
    "thigh": 0.228,
    "shank": 0.250,
    "foot": 0.140,
    "ankle_height": 0.039,
    "hip_breadth": 0.191,
    "shoulder_breadth": 0.200,  # chest at the armpits
    "head_breadth": 0.088,
    "head_depth": 0.110,
    "hand_breadth": 0.049,
    "foot_breadth": 0.055,
}


def segment_parameters(segment: str, sex: str = "average") -> SegmentParameters:
    """de Leva's Table 4 row of ``segment`` for ``sex`` (male, female or average)."""
    if sex not in SEX:
        raise UserError(f"sex must be one of {SEX}, got {sex!r}")
    if sex == "average":
        row = tuple(0.5 * (a + b) for a, b in zip(*_TABLE4[segment]))
    else:
        row = _TABLE4[segment][_SEX_COLUMN[sex]]
    return SegmentParameters(*(v / 100.0 for v in row))


def mass_fractions(sex: str = "average") -> dict[str, float]:
    """Fraction of body mass of each segment (limbs: one side). Sums to 1 over the body."""
    return {name: segment_parameters(name, sex).mass for name in _TABLE4}
