"""What a humanoid BVH skeleton from the wild is made of (numpy only).

:func:`analyse` gives a clip's :class:`Anatomy`: every joint labelled with the body segment it
carries, its side and its mirror joint, the world up axis, the facing direction, a reference
frame and the pose the body shapes are built on (:mod:`neuromotor.model.labels`), the stature
and the length unit (:mod:`neuromotor.model.units`: ``units="auto"`` picks the unit in
:data:`UNIT_CHOICES` that makes a plausible adult). :func:`prepare_clip` chains reading,
skipping bind-pose frames, removing a virtual root (:mod:`neuromotor.model.clip_edit`) and the
analysis.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from neuromotor.model.bvh import BvhClip, read_bvh, rest_pose_positions
from neuromotor.model.clip_edit import collapse_virtual_root, scale_clip, skip_rest_frames
from neuromotor.model.labels import DETAIL_SEGMENTS, SEGMENTS, label_joints
from neuromotor.model.units import UNIT_SCALES, auto_scale, check_stature, choose_units, resolve_units

__all__ = ["SEGMENTS", "DETAIL_SEGMENTS", "UNIT_CHOICES", "Anatomy", "analyse", "prepare_clip"]

UNIT_CHOICES = UNIT_SCALES  # metres per file unit, by name


@dataclasses.dataclass(frozen=True)
class Anatomy:
    """Per-joint labels (same order as the analysed clip's joints) and whole-body facts."""

    segment: tuple[str, ...]  # one of SEGMENTS per joint
    side: tuple[str, ...]  # "left" | "right" | ""
    mirror: tuple[int, ...]  # index of the mirror-image joint, -1 if none
    up: np.ndarray  # (3,) world up, a signed unit coordinate axis
    forward: np.ndarray  # (3,) unit facing direction (at reference_frame), perpendicular to up
    reference_frame: int  # frame of the clip where the character stands most upright
    stature: float  # metres
    length_scale: float  # metres per file unit
    units: str  # key of UNIT_CHOICES, "given" or "scaled"
    warnings: tuple[str, ...]
    limb_chains: dict  # "arm_left", "arm_right", "leg_left", "leg_right", "head", "spine" -> joint indices
    # The pose the body shapes are built on: None is the zero pose (every rotation channel 0, the
    # skeleton alone), used when it is a standing pose; else a frame of the clip (reference_frame).
    # shape_up and shape_forward are up and facing in that pose (None: up and forward).
    shape_frame: int | None = None
    shape_up: np.ndarray | None = None
    shape_forward: np.ndarray | None = None

    @property
    def humanoid(self) -> bool:
        """Arms and legs were found (else every joint is "trunk" and bodies get generic shapes)."""
        return bool(self.limb_chains)

    @property
    def up_axis(self) -> int:
        return int(np.flatnonzero(self.up)[0])

    def joints_of(self, *segments: str) -> tuple[int, ...]:
        """Indices of the joints labelled with any of ``segments``."""
        return tuple(k for k, s in enumerate(self.segment) if s in segments)


def analyse(clip: BvhClip, units="auto", stature: float | None = None) -> Anatomy:
    """Anatomy of ``clip``, whose lengths are taken as file units (read it with ``units=1.0``).

    ``units``: "auto", a key of :data:`UNIT_CHOICES` or a positive number of metres per file unit.
    ``stature`` (metres): with "auto", sets the scale (units "given"); with explicit units, is
    reported as the stature.
    """
    fixed = resolve_units(units)
    stature = check_stature(stature)
    found = label_joints(clip)
    warnings = list(found.warnings)
    person = bool(found.limb_chains)
    if not person and fixed is None and stature is None:  # not a person: no stature to go by
        fixed = auto_scale(_rest_points(clip))
    scale, unit_name, stat = choose_units(found.height, fixed, stature, warnings)
    if person:
        _translation_warnings(clip, scale, warnings)
    labels = Anatomy(
        found.segment,
        found.side,
        found.mirror,
        found.up,
        found.forward,
        found.reference_frame,
        stat,
        scale,
        unit_name,
        tuple(warnings),
        {},
    )
    if not person:  # generic shapes: the offsets alone
        return labels
    return dataclasses.replace(
        labels,
        limb_chains=found.limb_chains,
        shape_frame=found.shape_frame,
        shape_up=found.shape_up,
        shape_forward=found.shape_forward,
    )


def _rest_points(clip: BvhClip) -> np.ndarray:
    """(N, 3) joint and End Site positions of the zero-rotation rest pose (file units)."""
    pos = rest_pose_positions(clip)
    ends = [pos[k] + j.end_site for k, j in enumerate(clip.joints) if j.end_site is not None]
    return np.concatenate([pos, np.reshape(ends, (-1, 3))])


def _translation_warnings(clip: BvhClip, scale: float, warnings: list[str]) -> None:
    """A warning per non-root joint whose translation channels move it (their mean is used)."""
    for k, joint in enumerate(clip.joints):
        cols = joint.translation_columns
        if k == 0 or not cols:
            continue
        values = clip.motion[:, list(cols)]
        move = float(np.linalg.norm(values - values.mean(axis=0), axis=1).max()) * scale
        if move > 0.01:
            warnings.append(
                f"joint {joint.name!r}: translation channels move it by up to {100 * move:.3g} cm; "
                f"its mean offset is used"
            )


def prepare_clip(path_or_clip, units="auto", stature: float | None = None) -> tuple[BvhClip, Anatomy, BvhClip]:
    """Read a BVH file (or take a clip), collapse a virtual root, analyse it.

    Returns (clip in metres ready for the model, its anatomy, the source clip in metres with the
    same length_scale, for export). The anatomy's warnings start with the parser's and the
    collapse's."""
    if isinstance(path_or_clip, BvhClip):
        raw = path_or_clip
        if raw.length_scale != 1.0:  # back to file units
            raw = scale_clip(raw, 1.0 / raw.length_scale)
            raw = dataclasses.replace(raw, length_scale=1.0)
    else:
        raw = read_bvh(os.fspath(path_or_clip), units=1.0)
    raw, skip_warnings = skip_rest_frames(raw)
    collapsed, _, collapse_warnings = collapse_virtual_root(raw)
    anatomy = analyse(collapsed, units=units, stature=stature)
    anatomy = dataclasses.replace(
        anatomy, warnings=tuple(raw.warnings) + skip_warnings + collapse_warnings + anatomy.warnings
    )
    return scale_clip(collapsed, anatomy.length_scale), anatomy, scale_clip(raw, anatomy.length_scale)
