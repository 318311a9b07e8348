"""Export of the character to MuJoCo's MJCF (for cross-checks against MuJoCo and speed comparisons).

    xml = model_to_mjcf(character)
    export_mjcf(character, "character.xml")

The MJCF describes the same skeleton and mass model as :class:`neuromotor.model.skeleton.Model`:

* one MuJoCo body per model body, nested as the tree (joints without a body, the massless
  leaves, are skipped); the body frame is the BVH joint frame, so a body's ``pos`` is its
  joint's fixed offset in the parent joint's frame and its rest rotation is the identity;
* ``<inertial pos=com mass=m fullinertia="ixx iyy izz ixy ixz iyz"/>`` from ``model.com``,
  ``model.mass`` and ``model.inertia`` (about the COM, body frame); ``inertiafromgeom="false"``
  so the drawing geoms add no mass;
* the root body has a ``<freejoint/>`` named after the root joint. MuJoCo's free joint state is
  ``qpos = [origin (world), quat (w, x, y, z)]``, ``qvel = [origin velocity (world), angular
  velocity (root body frame)]``, and its generalized force is ``[force (world) at the body
  origin, torque about the body origin (root body frame)]``;
* every other body has one hinge per rotation channel, named like our DOFs
  (``"LeftKnee.Zrotation"``; MuJoCo accepts dots in names), axes ``e_a1, e_a2, e_a3`` in the
  channel order. MuJoCo composes the hinges of one body in order,
  ``R_body = R_parent R_a1(q1) R_a2(q2) R_a3(q3)``, which is exactly the BVH Euler convention
  (``skeleton.Model.joint_order``), so hinge qpos are our Euler angles theta (radians) and the
  hinge generalized force is ``h_i . T`` with ``T`` the world torque of the joint on its child;
* capsules along each bone for viewing only (``contype=0 conaffinity=0``, no mass);
* ``<option gravity=model.gravity timestep integrator="implicitfast">``;
* one ``<position>`` servo (PD, ``kp``/``kv``) per hinge, named like the hinge.

Units are SI (metres, kilograms, seconds, radians).
"""

from __future__ import annotations

import pathlib
import xml.etree.ElementTree as ET

import numpy as np

from neuromotor.atomic import atomic_path
from neuromotor.errors import UserError
from neuromotor.model.skeleton import Character

AXIS_VEC = {"X": "1 0 0", "Y": "0 1 0", "Z": "0 0 1"}


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def _check_params(timestep, kp, kv) -> None:
    for key, value, low in (("timestep", timestep, None), ("kp", kp, 0.0), ("kv", kv, 0.0)):
        ok = (
            not isinstance(value, bool)
            and isinstance(value, (int, float, np.integer, np.floating))
            and np.isfinite(value)
            and (value > 0 if low is None else value >= low)
        )
        if not ok:
            raise UserError(f"MJCF {key} must be a finite number {'> 0' if low is None else '>= 0'}, got {value!r}")


def _header(root, model, timestep: float) -> None:
    """Compiler, option (gravity, step, integrator) and defaults."""
    ET.SubElement(root, "compiler", angle="radian", inertiafromgeom="false", autolimits="true")
    ET.SubElement(
        root, "option", gravity=_fmt(model.gravity), timestep=repr(float(timestep)), integrator="implicitfast"
    )
    default = ET.SubElement(root, "default")
    ET.SubElement(default, "joint", damping="0", armature="0", limited="false")
    ET.SubElement(default, "geom", contype="0", conaffinity="0", mass="0", rgba="0.7 0.6 0.5 1")


class _BodyTree:
    """Writes the character's bodies as nested MJCF bodies, collecting the hinge names."""

    def __init__(self, character: Character):
        model = character.model
        self.model = model
        self.mass = np.asarray(model.mass, dtype=np.float64)
        self.com = np.asarray(model.com, dtype=np.float64)
        self.inertia = np.asarray(model.inertia, dtype=np.float64)
        self.offsets = np.asarray(model.joint_offset, dtype=np.float64)
        self.end_offsets = np.asarray(model.end_site_offset, dtype=np.float64).reshape(-1, 3)
        self.radii = np.asarray(character.radii, dtype=np.float64)
        self.children: dict[int, list[int]] = {}
        for k, p in enumerate(model.joint_parent):
            self.children.setdefault(p, []).append(k)
        self.ends: dict[int, list[int]] = {}
        for e, k in enumerate(model.end_site_joint):
            self.ends.setdefault(k, []).append(e)
        self.hinges: list[str] = []

    def add_body(self, parent_el, b: int) -> None:
        model, names = self.model, self.model.joint_names
        k = model.body_joint[b]
        body = ET.SubElement(parent_el, "body", name=names[k], pos=_fmt(self.offsets[k]))
        i = self.inertia[b]
        ET.SubElement(
            body,
            "inertial",
            pos=_fmt(self.com[b]),
            mass=repr(float(self.mass[b])),
            fullinertia=_fmt([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]),
        )
        if model.body_parent[b] < 0:
            ET.SubElement(body, "freejoint", name=names[k])
        else:
            for axis in model.joint_order[k]:
                hinge = f"{names[k]}.{axis}rotation"
                ET.SubElement(body, "joint", name=hinge, type="hinge", axis=AXIS_VEC[axis], pos="0 0 0")
                self.hinges.append(hinge)
        self.add_geoms(body, k)
        for c in self.children.get(k, []):
            cb = model.joint_body[c]
            if cb >= 0:
                self.add_body(body, cb)

    def add_geoms(self, body, k: int) -> None:
        """Viewing geoms: one capsule per bone (to each child joint and End Site), else a sphere."""
        r = float(max(self.radii[k], 1e-3))
        bone_ends = [self.offsets[c] for c in self.children.get(k, [])] + [
            self.end_offsets[e] for e in self.ends.get(k, [])
        ]
        drawn = False
        for end in bone_ends:
            if np.linalg.norm(end) > 1e-6:
                ET.SubElement(
                    body, "geom", type="capsule", size=repr(r), fromto=_fmt(np.concatenate([np.zeros(3), end]))
                )
                drawn = True
        if not drawn:
            ET.SubElement(body, "geom", type="sphere", size=repr(r))


def model_to_mjcf(
    character: Character,
    timestep: float = 1.0 / 120.0,
    kp: float = 100.0,
    kv: float = 10.0,
    name: str | None = None,
) -> str:
    """MJCF XML text of the character (see the module docstring for the conventions).
    ``timestep`` must be a finite number of seconds > 0, ``kp`` and ``kv`` finite and >= 0."""
    _check_params(timestep, kp, kv)
    root = ET.Element("mujoco", model=name or pathlib.Path(str(character.clip.path)).stem)
    _header(root, character.model, timestep)
    tree = _BodyTree(character)
    tree.add_body(ET.SubElement(root, "worldbody"), 0)
    actuator = ET.SubElement(root, "actuator")
    for hinge in tree.hinges:
        ET.SubElement(actuator, "position", name=hinge, joint=hinge, kp=repr(float(kp)), kv=repr(float(kv)))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def export_mjcf(character: Character, path, **kwargs) -> pathlib.Path:
    """Write :func:`model_to_mjcf` to ``path`` atomically (temp file in the same folder + replace)."""
    path = pathlib.Path(path)
    text = model_to_mjcf(character, **kwargs)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
