"""Skeleton and mass model in maximal coordinates (Sections 4 and 5.1 of the paper).

One rigid body per BVH joint that carries a segment of the body. The body's frame is the joint's
frame (origin at the joint, axes of the BVH joint); its shape is a convex polyhedron and its mass,
centre of mass and inertia are integrated exactly from that polyhedron at the density of water
(Section 5.1: "approximating the shape of the character with polyhedra ... assuming the density
of water").

Which joints are bodies, and the shapes, come from the clip's anatomy
(:mod:`neuromotor.model.anatomy`: every joint labelled trunk, head, upper arm, forearm, hand, thigh,
shank, foot or extremity detail from the skeleton's topology and bone lengths) and the
anthropometric mass model (:mod:`neuromotor.model.massmodel`: de Leva's segment masses, shapes a
person would recognise):

* Every joint that is not extremity detail and carries a bone, and every hand, foot and skull
  joint (even with a zero-length End Site), is a body; so is a zero-length link with bodies
  below it (a small block, so every joint between two bodies is a proper ball joint).
* Extremity detail (fingers, toes, face, eyes) is by default no body: its mass counts in the hand,
  foot or head, and its angles follow the capture relative to its parent (not simulated DOFs,
  still drawn and exported). ``MassModelOptions.simulate_extremities`` makes them bodies.
* Translation channels on non-root joints are replaced by their mean over the clip (joints are
  ball joints with fixed offsets); the root keeps its full 6-DOF path. A virtual root (a ground
  marker whose child carries the translation) has been removed before (see
  :func:`neuromotor.model.anatomy.prepare_clip`).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.errors import UserError
from neuromotor.model import polyhedron as poly
from neuromotor.model.anatomy import Anatomy, analyse
from neuromotor.model.bvh import BvhClip
from neuromotor.model.massmodel import plan_bodies, plan_generic
from neuromotor.model.topology import Topology, of as topology_of


@dataclasses.dataclass(frozen=True)
class MassModelOptions:
    """Parameters of the anthropometric mass model (see :mod:`neuromotor.model.massmodel`).

    ``body_mass`` (kg) defaults to a BMI of 22 at the clip's stature; ``sex`` picks de Leva's
    column (male, female or average); ``simulate_extremities`` makes fingers, toes and face
    joints bodies with simulated DOFs."""

    density: float = 1000.0
    body_mass: float | None = None
    sex: str = "average"
    simulate_extremities: bool = False
    sides: int = 10


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
    gravity: Float[Array, 3]

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

    @property
    def topology(self) -> Topology:
        """Static index arrays of the joint and body trees (built once per skeleton shape)."""
        return topology_of(self)


def scale_masses(model: Model, body_mass=None, body_scale=None) -> Model:
    """The same shapes at another total mass and/or per-body mass factors (B,): masses and
    inertias scale together (the density changes, the geometry does not). Pure array maths,
    so ``body_mass`` and ``body_scale`` can be fitted or swept (jit, vmap, grad)."""
    factor = jnp.ones_like(model.mass)
    if body_scale is not None:
        factor = factor * jnp.asarray(body_scale, model.mass.dtype)
    if body_mass is not None:
        factor = factor * (jnp.asarray(body_mass, model.mass.dtype) / jnp.sum(model.mass * factor))
    return dataclasses.replace(model, mass=model.mass * factor, inertia=model.inertia * factor[:, None, None])


@dataclasses.dataclass(frozen=True)
class Character:
    """A model together with its source clip, anatomy and body shapes (for rendering and contact)."""

    model: Model
    clip: BvhClip  # the clip the model is built on (metres; a virtual root removed)
    shapes: tuple[poly.Polyhedron | None, ...]  # per body, in the body frame
    radii: np.ndarray  # (J,) drawing radius of each joint's bone
    options: MassModelOptions
    anatomy: Anatomy | None = None
    body_segment: tuple[str, ...] = ()  # mass-budget segment of each body
    source_clip: BvhClip | None = None  # the file as read (metres), for export
    warnings: tuple[str, ...] = ()

    @property
    def source(self) -> BvhClip:
        return self.source_clip if self.source_clip is not None else self.clip


def joint_offsets(clip: BvhClip) -> np.ndarray:
    """(J,3) fixed offsets in metres; non-root translation channels replaced by their mean."""
    offsets = np.array([j.offset for j in clip.joints], dtype=np.float64)
    for k, joint in enumerate(clip.joints):
        cols = joint.translation_columns
        if cols and joint.parent >= 0:
            offsets[k] = clip.motion[:, list(cols)].mean(axis=0)
    return offsets


def _plan(clip: BvhClip, anatomy: Anatomy, offsets: np.ndarray, options: MassModelOptions):
    """Which joints are bodies and their shapes and masses: the anthropometric model for a
    person, generic shapes otherwise."""
    if anatomy.humanoid:
        return plan_bodies(
            clip,
            anatomy,
            offsets,
            body_mass=options.body_mass,
            sex=options.sex,
            density=options.density,
            simulate_extremities=options.simulate_extremities,
            sides=options.sides,
        )
    return plan_generic(clip, offsets, options.density)


def _body_parents(clip: BvhClip, joint_body: list[int], body_joint) -> list[int]:
    body_parent = []
    for k in body_joint:
        p = clip.joints[k].parent
        body_parent.append(joint_body[p] if p >= 0 else -1)
        if p >= 0 and joint_body[p] < 0:  # cannot happen: ancestors of bodies have bodies
            raise AssertionError("body with a massless parent joint")
    return body_parent


def _bone_radii(n_joints: int, stature: float, body_joint, shapes) -> np.ndarray:
    """Drawing radius per joint: half the median distance of its body's vertices from their
    centre, at least 1.2 % of the stature."""
    radii = np.full(n_joints, 0.012 * float(stature))
    for b, k in enumerate(body_joint):
        v = shapes[b].vertices
        radii[k] = max(radii[k], 0.5 * float(np.median(np.linalg.norm(v - v.mean(0), axis=1))))
    return radii


@dataclasses.dataclass
class _Dofs:
    """Every rotation channel of a non-root joint; the simulated ones (joint has a body) apart."""

    all_names: list[str] = dataclasses.field(default_factory=list)
    sim_columns: list[int] = dataclasses.field(default_factory=list)
    body: list[int] = dataclasses.field(default_factory=list)
    slot: list[int] = dataclasses.field(default_factory=list)
    names: list[str] = dataclasses.field(default_factory=list)


def _dofs(clip: BvhClip, joint_body: list[int]) -> _Dofs:
    out = _Dofs()
    for k, j in enumerate(clip.joints):
        if j.parent < 0:
            continue
        for slot, axis in enumerate(j.rotation_order):
            name = f"{j.name}.{axis}rotation"
            if joint_body[k] >= 0:
                out.sim_columns.append(len(out.all_names))
                out.names.append(name)
                out.body.append(joint_body[k])
                out.slot.append(slot)
            out.all_names.append(name)
    return out


def _check_channels(clip: BvhClip, joint_body: list[int]) -> None:
    """The root needs 6 channels (driven along the mocap); every body joint three rotations."""
    joints = clip.joints
    if joints[0].rotation_order == "" or len(joints[0].translation_columns) == 0:
        raise UserError(
            f"{clip.path}: root joint {joints[0].name!r} needs 3 position and 3 "
            "rotation channels to be driven along the mocap path"
        )
    for k, j in enumerate(joints):
        if j.parent >= 0 and joint_body[k] >= 0 and j.rotation_order == "":
            raise UserError(
                f"{clip.path}:{j.line}: joint {j.name!r} carries a body but has no "
                "rotation channels; ball joints need three"
            )


def _gravity(anatomy: Anatomy, up_axis: int | None, gravity) -> np.ndarray:
    """Gravity: ``gravity`` if given, else 9.81 m/s^2 against the up axis (``up_axis`` or the
    anatomy's)."""
    if gravity is not None:
        return np.asarray(gravity, dtype=np.float64)
    up = np.asarray(anatomy.up, dtype=np.float64)
    if up_axis is not None:
        up = np.eye(3)[int(up_axis)]
    return -9.81 * up


def build_character(
    clip: BvhClip,
    options: MassModelOptions | None = None,
    gravity: tuple[float, float, float] | None = None,
    up_axis: int | None = None,
    anatomy: Anatomy | None = None,
    source_clip: BvhClip | None = None,
) -> Character:
    """Build the maximal-coordinate model of a clip in metres (bodies, masses, joints, DOFs).

    ``anatomy`` labels the joints (default: :func:`neuromotor.model.anatomy.analyse` of ``clip``
    taken as metres); ``up_axis`` (0, 1, 2) overrides the up axis found from the motion."""
    options = options or MassModelOptions()
    if anatomy is None:
        anatomy = analyse(clip, units=1.0)
    joints = clip.joints
    offsets = joint_offsets(clip)
    plan = _plan(clip, anatomy, offsets, options)
    joint_body, body_joint = list(plan.joint_body), plan.body_joint
    body_parent = _body_parents(clip, joint_body, body_joint)
    radii = _bone_radii(len(joints), anatomy.stature, body_joint, plan.shapes)
    dofs = _dofs(clip, joint_body)
    _check_channels(clip, joint_body)
    end_joint = tuple(k for k, j in enumerate(joints) if j.end_site is not None)
    end_off = np.array([joints[k].end_site for k in end_joint], dtype=np.float64).reshape(-1, 3)
    model = Model(
        joint_names=tuple(j.name for j in joints),
        joint_parent=tuple(j.parent for j in joints),
        joint_order=tuple(j.rotation_order for j in joints),
        joint_body=tuple(joint_body),
        body_names=tuple(joints[k].name for k in body_joint),
        body_joint=tuple(body_joint),
        body_parent=tuple(body_parent),
        dof_names=tuple(dofs.names),
        dof_body=tuple(dofs.body),
        dof_slot=tuple(dofs.slot),
        all_dof_names=tuple(dofs.all_names),
        sim_dof_columns=tuple(dofs.sim_columns),
        end_site_joint=end_joint,
        mass=jnp.asarray(plan.mass),
        inertia=jnp.asarray(plan.inertia),
        com=jnp.asarray(plan.com),
        joint_offset=jnp.asarray(offsets),
        end_site_offset=jnp.asarray(end_off),
        gravity=jnp.asarray(_gravity(anatomy, up_axis, gravity)),
    )
    # The anatomy's warnings start with the parser's, which the clip carries too: each once.
    warnings = tuple(dict.fromkeys(tuple(getattr(clip, "warnings", ())) + tuple(anatomy.warnings)))
    return Character(
        model=model,
        clip=clip,
        shapes=plan.shapes,
        radii=radii,
        options=options,
        anatomy=anatomy,
        body_segment=plan.body_segment,
        source_clip=source_clip,
        warnings=warnings,
    )


BODY_KEYWORDS = ("pelvis", "chest", "head") + tuple(
    f"{side}_{seg}" for side in ("left", "right") for seg in ("upper_arm", "forearm", "hand", "thigh", "shank", "foot")
)


def keyword_body(character: Character, keyword: str) -> int | None:
    """Body index of a segment keyword (``chest``, ``pelvis``, ``head``, ``left_hand``, ...), so a
    config can name a place on any skeleton: ``chest`` is the trunk body the arms hang from,
    ``pelvis`` the one the legs hang from, ``head`` the skull. None if the rig has no such body."""
    anat, model = character.anatomy, character.model
    if anat is None or keyword not in BODY_KEYWORDS:
        return None
    seg = anat.segment
    parent = model.joint_parent
    if keyword in ("pelvis", "chest"):
        limb = "thigh" if keyword == "pelvis" else "upper_arm"
        tops = [k for k in range(len(seg)) if seg[k] == limb and seg[parent[k]] != limb]
        if not tops:
            return None
        paths = []
        for k in tops:
            path = []
            while k >= 0:
                path.append(k)
                k = parent[k]
            paths.append(path[::-1])
        common = [a for a, *rest in zip(*paths) if all(r == a for r in rest)]
        bodies = [k for k in common if model.joint_body[k] >= 0 and seg[k] == "trunk"]
        return model.joint_body[bodies[-1]] if bodies else None
    if keyword == "head":
        heads = [k for k in range(len(seg)) if seg[k] == "head" and model.joint_body[k] >= 0]
        return model.joint_body[heads[-1]] if heads else None
    side, segment = keyword.split("_", 1)
    found = [k for k in range(len(seg)) if seg[k] == segment and anat.side[k] == side and model.joint_body[k] >= 0]
    return model.joint_body[found[0]] if found else None


def unknown_body(model: Model, character: Character | None, name: str) -> str:
    """What an error says of a body ``name`` that is neither a body of ``model`` nor a keyword
    this rig resolves: the bodies, and only the segment keywords its labels find."""
    found = [k for k in BODY_KEYWORDS if character is not None and keyword_body(character, k) is not None]
    what = (
        f"{name!r} is a segment keyword this rig's labels do not find"
        if name in BODY_KEYWORDS
        else f"unknown body {name!r}"
    )
    keywords = f" (or one of {', '.join(found)})" if found else " (its labels find no segment keyword)"
    return f"{what}; bodies are {', '.join(model.body_names)}{keywords}"


# Group keywords of a restraint (``[sim] driven_joints``): the anatomy's segment labels each
# takes (what ``neuromotor inspect`` prints per joint); ``pelvis`` is the one body of
# :func:`keyword_body`.
GROUP_KEYWORDS: dict[str, tuple[str, ...]] = {
    "trunk": ("trunk",),
    "pelvis": (),
    "legs": ("thigh", "shank", "foot"),
    "arms": ("upper_arm", "forearm", "hand"),
    "head": ("head",),
}
RESTRAINT_KEYWORDS = tuple(GROUP_KEYWORDS) + tuple(k for k in BODY_KEYWORDS if k not in GROUP_KEYWORDS)


def keyword_bodies(character: Character, keyword: str) -> tuple[int, ...] | None:
    """The bodies a restraint keyword names, in body order: a group of :data:`GROUP_KEYWORDS`
    (``trunk``: every body whose joint is labelled trunk, the root included; ``legs``: thigh,
    shank and foot; ``arms``: upper arm, forearm and hand; ``head``: every head-labelled body;
    ``pelvis``: the pelvis body), else a single-body keyword of :data:`BODY_KEYWORDS`. ``()``
    when the keyword matches no body of this rig (no arms, no anatomy), None when ``keyword``
    is not a keyword. The one rule of :func:`neuromotor.studies.simulate.prepare`."""
    if keyword not in RESTRAINT_KEYWORDS:
        return None
    if keyword in GROUP_KEYWORDS and GROUP_KEYWORDS[keyword]:
        anat, model = character.anatomy, character.model
        if anat is None:
            return ()
        labels = GROUP_KEYWORDS[keyword]
        return tuple(sorted(model.joint_body[k] for k in anat.joints_of(*labels) if model.joint_body[k] >= 0))
    b = keyword_body(character, keyword)
    return () if b is None else (b,)
