"""Skeleton and mass model in maximal coordinates (Sections 4 and 5.1 of the paper).

One rigid body per BVH joint that carries a bone. The body's frame is the joint's frame (origin
at the joint, axes of the BVH joint); its shape is a convex polyhedron that wraps its bones, and
its mass, centre of mass and inertia are integrated exactly from that polyhedron at the density
of water (Section 5.1: "approximating the shape of the character with polyhedra ... assuming the
density of water").

Radius rule (each bone j -> child or End Site of length L is wrapped by an 8-sided prism, and a
body is the convex hull of the prisms of all its bones):

* limb bones: radius = ``limb_radius_ratio * L`` (0.15 by default; gives thigh ~7 kg, shank
  ~3.5 kg for an adult);
* trunk bodies, those with two or more leaves (End Sites) below them: radius =
  ``trunk_radius_ratio * span``, where ``span`` is the skeleton's largest leaf-to-leaf path length
  (hand to foot), a pose-independent size;
* head: a body whose joint, or whose massless leaf child, is named like ``head`` uses radius =
  ``head_radius_ratio * L``;
* every radius is at least ``min_radius``.

Well-posedness rule:

* A bone shorter than ``min_bone_length`` does not count. A joint whose subtree has no bone that
  counts carries no body: its rotational DOFs are not simulated (nothing is moved by them; their
  torque is zero). Example: the zero-length End Sites of hands, toes and head in the walk clip.
* A joint with a short bone but with bodies below it (a zero-length link inside a chain) gets a
  body all the same, padded to a cube of half-size ``min_radius``, so every joint between two
  bodies is a proper ball joint.
* Translation channels on non-root joints are replaced by their mean over the clip (joints are
  ball joints with fixed offsets); the root keeps its full 6-DOF path.
"""

from __future__ import annotations

import dataclasses
import re

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import polyhedron as poly
from .bvh import BvhClip

HEAD_PATTERN = re.compile("head", re.IGNORECASE)


@dataclasses.dataclass(frozen=True)
class MassModelOptions:
    """Parameters of the polyhedral mass model (see the module docstring)."""

    density: float = 1000.0
    limb_radius_ratio: float = 0.15
    trunk_radius_ratio: float = 0.055
    head_radius_ratio: float = 0.5
    min_radius: float = 0.02
    min_bone_length: float = 0.03
    sides: int = 8


class Model(eqx.Module):
    """The character: static topology (metadata) plus array parameters (pytree leaves).

    Bodies are in BVH depth-first order, so a parent always precedes its children. Body 0 is the
    root. Generalized velocity layout: body b occupies entries ``6b:6b+3`` (COM velocity, world)
    and ``6b+3:6b+6`` (angular velocity, world).
    """

    # -- static topology
    joint_names: tuple[str, ...] = eqx.field(static=True)
    joint_parent: tuple[int, ...] = eqx.field(static=True)
    joint_order: tuple[str, ...] = eqx.field(static=True)  # rotation order, "" if none
    joint_body: tuple[int, ...] = eqx.field(static=True)  # body index or -1
    body_names: tuple[str, ...] = eqx.field(static=True)
    body_joint: tuple[int, ...] = eqx.field(static=True)
    body_parent: tuple[int, ...] = eqx.field(static=True)
    dof_names: tuple[str, ...] = eqx.field(static=True)  # simulated DOFs, "JOINT.Zrotation"
    dof_body: tuple[int, ...] = eqx.field(static=True)  # the child body the DOF turns
    dof_slot: tuple[int, ...] = eqx.field(static=True)  # 0, 1, 2: place in the joint's order
    all_dof_names: tuple[str, ...] = eqx.field(static=True)  # every non-root rotation channel
    sim_dof_columns: tuple[int, ...] = eqx.field(static=True)  # index of each DOF in all_dof_names
    end_site_joint: tuple[int, ...] = eqx.field(static=True)  # joint owning each End Site
    # -- array parameters
    mass: Float[Array, " B"]
    inertia: Float[Array, "B 3 3"]  # about the COM, body frame
    com: Float[Array, "B 3"]  # COM in the body (joint) frame
    joint_offset: Float[Array, "J 3"]  # joint origin in its parent joint's frame
    end_site_offset: Float[Array, "E 3"]
    gravity: Float[Array, "3"]

    @property
    def n_bodies(self) -> int:
        return len(self.body_names)

    @property
    def n_dofs(self) -> int:
        return len(self.dof_names)

    @property
    def n_constraints(self) -> int:
        """6 driven root rows plus 3 point-coincidence rows per ball joint."""
        return 6 + 3 * (self.n_bodies - 1)

    def dofs_of_body(self, b: int) -> tuple[int, ...]:
        return tuple(i for i, db in enumerate(self.dof_body) if db == b)


@dataclasses.dataclass(frozen=True)
class Character:
    """A model together with its source clip and body shapes (for rendering and contact)."""

    model: Model
    clip: BvhClip
    shapes: tuple[poly.Polyhedron | None, ...]  # per body, in the body frame
    radii: np.ndarray  # (J,) drawing radius of each joint's bone
    options: MassModelOptions


def _leaf_counts(children: list[list[int]], has_end: list[bool]) -> list[int]:
    counts = [0] * len(children)
    for j in reversed(range(len(children))):
        counts[j] = int(has_end[j] or not children[j]) + sum(counts[c] for c in children[j])
    return counts


def _tree_span(clip: BvhClip, offsets: np.ndarray, children: list[list[int]]) -> float:
    """Largest leaf-to-leaf path length along bones (the tree's weighted diameter)."""
    n = len(clip.joints)
    best = 0.0
    depth = [0.0] * n  # longest downward path from joint j to a leaf
    for j in reversed(range(n)):
        paths = [depth[c] + float(np.linalg.norm(offsets[c])) for c in children[j]]
        if clip.joints[j].end_site is not None:
            paths.append(float(np.linalg.norm(clip.joints[j].end_site)))
        paths.sort(reverse=True)
        depth[j] = paths[0] if paths else 0.0
        if len(paths) >= 2:
            best = max(best, paths[0] + paths[1])
        best = max(best, depth[j])
    return best


def joint_offsets(clip: BvhClip) -> np.ndarray:
    """(J,3) fixed offsets in metres; non-root translation channels replaced by their mean."""
    offsets = np.array([j.offset for j in clip.joints], dtype=np.float64)
    for k, joint in enumerate(clip.joints):
        cols = joint.translation_columns
        if cols and joint.parent >= 0:
            offsets[k] = clip.motion[:, list(cols)].mean(axis=0)
    return offsets


def build_character(
    clip: BvhClip,
    options: MassModelOptions | None = None,
    gravity: tuple[float, float, float] | None = None,
    up_axis: int = 1,
) -> Character:
    """Build the maximal-coordinate model of a BVH clip (bodies, masses, joints, DOFs)."""
    options = options or MassModelOptions()
    joints = clip.joints
    n = len(joints)
    offsets = joint_offsets(clip)
    children: list[list[int]] = [[] for _ in range(n)]
    for k, j in enumerate(joints):
        if j.parent >= 0:
            children[j.parent].append(k)
    # Bones of each joint: (end point in joint frame, leaf name for the head rule).
    bones: list[list[tuple[np.ndarray, str]]] = [[] for _ in range(n)]
    for k, j in enumerate(joints):
        for c in children[k]:
            bones[k].append((offsets[c], joints[c].name))
        if j.end_site is not None:
            bones[k].append((np.asarray(j.end_site, dtype=np.float64), j.name))
    bone_len = [max((float(np.linalg.norm(e)) for e, _ in bones[k]), default=0.0) for k in range(n)]
    # A joint carries a body if a counted bone exists in its subtree (itself included).
    counts_below = [False] * n
    for k in reversed(range(n)):
        counts_below[k] = bone_len[k] >= options.min_bone_length or any(
            counts_below[c] for c in children[k]
        )
    if not counts_below[0]:
        raise ValueError(f"{clip.path}: the skeleton has no bone longer than "
                         f"{options.min_bone_length} m; nothing to simulate")
    has_body = counts_below
    leaves = _leaf_counts(children, [j.end_site is not None for j in joints])
    span = _tree_span(clip, offsets, children)

    joint_body = [-1] * n
    body_joint: list[int] = []
    for k in range(n):
        if has_body[k]:
            joint_body[k] = len(body_joint)
            body_joint.append(k)
    body_parent = []
    for k in body_joint:
        p = joints[k].parent
        body_parent.append(joint_body[p] if p >= 0 else -1)
        if p >= 0 and joint_body[p] < 0:  # cannot happen: ancestors of bodies have bodies
            raise AssertionError("body with a massless parent joint")

    shapes: list[poly.Polyhedron] = []
    masses, coms, inertias = [], [], []
    radii = np.zeros(n)
    for k in body_joint:
        segs = []
        is_trunk = leaves[k] >= 2
        massless_kids = [joints[c].name for c in children[k] if not has_body[c]]
        is_head = bool(HEAD_PATTERN.search(joints[k].name)) or any(
            HEAD_PATTERN.search(name) for name in massless_kids
        )
        for end, _name in bones[k]:
            length = float(np.linalg.norm(end))
            if length < options.min_bone_length:
                continue
            if is_trunk:
                r = options.trunk_radius_ratio * span
            elif is_head:
                r = options.head_radius_ratio * length
            else:
                r = options.limb_radius_ratio * length
            r = max(r, options.min_radius)
            radii[k] = max(radii[k], r)
            segs.append((np.zeros(3), end, r))
        if segs:
            shape = poly.segment_hull(segs, sides=options.sides)
        else:  # short link inside a chain: padded cube keeps the body well-conditioned
            shape = poly.box(np.full(3, options.min_radius))
            radii[k] = options.min_radius
        m, c, inertia = poly.mass_properties(shape, options.density)
        shapes.append(shape)
        masses.append(m)
        coms.append(c)
        inertias.append(inertia)
    for k in range(n):
        if radii[k] == 0.0:
            radii[k] = options.min_radius

    # DOFs: every rotation channel of a non-root joint; simulated if the joint has a body.
    all_dofs, sim_cols, dof_body, dof_slot, dof_names = [], [], [], [], []
    for k, j in enumerate(joints):
        if j.parent < 0:
            continue
        for slot, axis in enumerate(j.rotation_order):
            name = f"{j.name}.{axis}rotation"
            if has_body[k]:
                sim_cols.append(len(all_dofs))
                dof_names.append(name)
                dof_body.append(joint_body[k])
                dof_slot.append(slot)
            all_dofs.append(name)
    if joints[0].rotation_order == "" or len(joints[0].translation_columns) == 0:
        raise ValueError(f"{clip.path}: root joint {joints[0].name!r} needs 3 position and 3 "
                         "rotation channels to be driven along the mocap path")
    for k, j in enumerate(joints):
        if j.parent >= 0 and has_body[k] and j.rotation_order == "":
            raise ValueError(f"{clip.path}:{j.line}: joint {j.name!r} carries a body but has no "
                             "rotation channels; ball joints need three")

    end_joint = tuple(k for k, j in enumerate(joints) if j.end_site is not None)
    end_off = np.array([joints[k].end_site for k in end_joint], dtype=np.float64).reshape(-1, 3)
    g = np.zeros(3)
    g[up_axis] = -9.81
    if gravity is not None:
        g = np.asarray(gravity, dtype=np.float64)

    model = Model(
        joint_names=tuple(j.name for j in joints),
        joint_parent=tuple(j.parent for j in joints),
        joint_order=tuple(j.rotation_order for j in joints),
        joint_body=tuple(joint_body),
        body_names=tuple(joints[k].name for k in body_joint),
        body_joint=tuple(body_joint),
        body_parent=tuple(body_parent),
        dof_names=tuple(dof_names),
        dof_body=tuple(dof_body),
        dof_slot=tuple(dof_slot),
        all_dof_names=tuple(all_dofs),
        sim_dof_columns=tuple(sim_cols),
        end_site_joint=end_joint,
        mass=jnp.asarray(masses),
        inertia=jnp.asarray(np.stack(inertias)),
        com=jnp.asarray(np.stack(coms)),
        joint_offset=jnp.asarray(offsets),
        end_site_offset=jnp.asarray(end_off),
        gravity=jnp.asarray(g),
    )
    return Character(model=model, clip=clip, shapes=tuple(shapes), radii=radii, options=options)
