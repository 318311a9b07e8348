"""Export to OpenSim: the character as an ``.osim`` model, motions as ``.mot``, inverse dynamics
as ``.sto``.

    export_osim(character, "model.osim")
    write_motion("motion.mot", character.model, time, root_origin, root_rot, theta_sim)
    write_idyn_storage(folder, character, idyn_arrays(...))

The model (OpenSim 4 XML, written with ``xml.etree``: no ``opensim`` import needed to write it)
describes the same bodies as :class:`neuromotor.model.skeleton.Model` and as
:mod:`neuromotor.io.mjcf`:

* one ``Body`` per model body (massless leaf joints are skipped, their mass is in the parent),
  named after its BVH joint; the body frame is the BVH joint frame; ``mass``, ``mass_center``
  (``model.com``) and ``inertia`` ``[Ixx Iyy Izz Ixy Ixz Iyz]`` about the COM in the body frame
  (``model.inertia``), as OpenSim defines them;
* one ``CustomJoint`` per non-root body, ``<child>_joint``: the parent frame is an offset frame on
  the parent body at the joint's fixed offset (``model.joint_offset``), the child frame is the
  child body's own frame, and the ``SpatialTransform`` has one rotational coordinate per BVH
  rotation channel, in channel order: OpenSim composes them body-fixed,
  ``R = R_a1(q1) R_a2(q2) R_a3(q3)``, the BVH Euler convention, so the coordinates *are* our joint
  angles theta (``"LeftKnee.Zrotation"`` becomes ``LeftKnee_Zrotation``). A ``BallJoint`` is
  avoided on purpose: Simbody's ball mobilizer has quaternion q and angular-velocity u, while
  OpenSim's ``InverseDynamicsSolver`` sets ``u`` to the time derivative of each coordinate, so the
  Inverse Dynamics Tool would mis-read a ball joint's motion; a CustomJoint's speeds are exactly
  the coordinate rates;
* the root is driven by the mocap as in ``idyn`` (a 6-DOF joint whose generalized forces are the
  root wrench): a ``CustomJoint`` to ground with its three rotation channels (``Hips_Zrotation``
  ...) and three translations along the parent frame's axes (``Hips_Xposition`` ...);
* Y-up: the root joint's parent frame is an offset frame on ground rotated by
  :func:`ground_rotation` (our world to OpenSim's ground, taking ``-gravity`` to +Y), so every
  coordinate is in our world frame and ``gravity`` is ``(0, -|g|, 0)``; metres, kilograms, seconds;
* a sphere at each joint and a cylinder along each bone for viewing (no mass).

Storage files use OpenSim's header (``name``, ``version=1``, ``nRows``, ``nColumns``,
``inDegrees``, ``endheader``) and a ``time`` column first. A motion (``.mot``) has the model's
coordinates in degrees (rotations) and metres (translations); inverse dynamics (``.sto``) has
each coordinate's generalized force, ``<coordinate>_moment`` (N m) or ``<coordinate>_force`` (N),
in the model's coordinate order: what OpenSim's Inverse Dynamics Tool writes for this model. The
generalized force of a rotational coordinate is its world axis h_i dotted with the joint's torque
on its child (about the joint centre); the root's are the root wrench's torque about the root
joint origin on its three axes and its force along the world axes. docs/opensim.md has more.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import xml.etree.ElementTree as ET

import numpy as np

from neuromotor.errors import UserError
from neuromotor.io.tables import atomic_write
from neuromotor.model.skeleton import Character, Model
from neuromotor.rotations import AXIS
from neuromotor.rotations_np import axis_rotation, matrix_to_euler

ROTATION_RANGE = (-4.0 * np.pi, 4.0 * np.pi)  # unwrapped angles may pass +-2 pi; nothing is clamped
TRANSLATION_RANGE = (-100.0, 100.0)
OSIM_VERSION = "40600"


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def osim_name(text: str) -> str:
    """A BVH name as an OpenSim component name (letters, digits, ``_`` and ``-``)."""
    return re.sub(r"[^A-Za-z0-9_\-]", "_", str(text)) or "_"


@dataclasses.dataclass(frozen=True)
class Layout:
    """The exported model's names: bodies, joints and coordinates in the storage files' order
    (root rotations in channel order, root translations X Y Z, then each non-root body's
    rotations in channel order, bodies in model order)."""

    bodies: tuple[str, ...]
    coordinates: tuple[str, ...]
    rotational: tuple[bool, ...]
    body_coordinates: tuple[tuple[int, ...], ...]  # per body, its columns in ``coordinates``

    @property
    def force_labels(self) -> tuple[str, ...]:
        """Column names of the inverse-dynamics ``.sto`` (OpenSim's ``_moment``/``_force``)."""
        return tuple(c + ("_moment" if r else "_force") for c, r in zip(self.coordinates, self.rotational))


def layout(model: Model) -> Layout:
    """Names of the exported bodies and coordinates (unique after :func:`osim_name`)."""
    bodies = tuple(osim_name(n) for n in model.body_names)
    if len(set(bodies)) != len(bodies):
        raise UserError(
            "joint names collide once made OpenSim names (letters, digits, _ and -): "
            + ", ".join(sorted({b for b in bodies if bodies.count(b) > 1}))
        )
    if len(model.joint_order[model.body_joint[0]]) != 3:
        raise UserError(
            f"root joint {model.joint_names[model.body_joint[0]]!r} needs 3 rotation channels "
            "for an OpenSim model (its 6-coordinate joint to ground)"
        )
    coords: list[str] = []
    rotational: list[bool] = []
    per_body: list[tuple[int, ...]] = []
    for b, k in enumerate(model.body_joint):
        start = len(coords)
        coords += [f"{bodies[b]}_{a}rotation" for a in model.joint_order[k]]
        rotational += [True] * len(model.joint_order[k])
        if b == 0:
            coords += [f"{bodies[0]}_{a}position" for a in "XYZ"]
            rotational += [False] * 3
        per_body.append(tuple(range(start, len(coords))))
    return Layout(bodies, tuple(coords), tuple(rotational), tuple(per_body))


# ----------------------------------------------------------------------------------------------
# Frames
# ----------------------------------------------------------------------------------------------


def channel_rotation(angles, order: str) -> np.ndarray:
    """Body-fixed product ``R_a1(t1) R_a2(t2) ...`` of a joint's channels: (..., 3, 3)."""
    angles = np.asarray(angles, dtype=np.float64)
    out = np.broadcast_to(np.eye(3), angles.shape[:-1] + (3, 3)).copy()
    for i, a in enumerate(order):
        out = out @ axis_rotation(AXIS[a], angles[..., i])
    return out


def channel_axes(parent_rot, angles, order: str) -> np.ndarray:
    """World axes h_i (..., len(order), 3) of a joint's channels: h_1 = R_p e_a1,
    h_2 = R_p R_a1(t1) e_a2, h_3 = R_p R_a1(t1) R_a2(t2) e_a3."""
    angles = np.asarray(angles, dtype=np.float64)
    rot = np.broadcast_to(np.asarray(parent_rot, dtype=np.float64), angles.shape[:-1] + (3, 3))
    axes = []
    for i, a in enumerate(order):
        axes.append(rot[..., :, AXIS[a]])
        rot = rot @ axis_rotation(AXIS[a], angles[..., i])
    return np.stack(axes, -2)


def euler_angles(rot, order: str) -> np.ndarray:
    """Angles (..., 3) with ``channel_rotation(angles, order) == rot`` for a three-axis order, on
    the branch with the middle angle in [-pi/2, pi/2], unwrapped along the leading (time) axis."""
    angles = matrix_to_euler(rot, order)
    return np.unwrap(angles, axis=0) if angles.ndim > 1 else angles


def ground_rotation(gravity) -> np.ndarray:
    """Rotation taking our world to OpenSim's ground: ``-gravity`` (up) to +Y, by the smallest
    turn (a half turn about X when up is -Y; the identity without gravity)."""
    g = np.asarray(gravity, dtype=np.float64)
    norm = np.linalg.norm(g)
    if norm == 0.0:
        return np.eye(3)
    up, y = -g / norm, np.array([0.0, 1.0, 0.0])
    axis, c = np.cross(up, y), float(up @ y)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3) if c > 0 else axis_rotation(0, np.pi)
    k = axis / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * kx + (1.0 - c) * kx @ kx


def xyz_orientation(rot) -> np.ndarray:
    """OpenSim's ``orientation`` property of a frame: body-fixed X-Y-Z angles of ``rot``."""
    return euler_angles(rot, "XYZ")


def _turn_y_to(direction) -> np.ndarray:
    """A rotation taking +Y to ``direction`` (OpenSim cylinders lie along their frame's Y)."""
    return ground_rotation(-np.asarray(direction, dtype=np.float64)).T


# ----------------------------------------------------------------------------------------------
# Model XML
# ----------------------------------------------------------------------------------------------


def _coordinate(parent, name: str, rotational: bool) -> None:
    low, high = ROTATION_RANGE if rotational else TRANSLATION_RANGE
    c = ET.SubElement(parent, "Coordinate", name=name)
    for tag, text in (
        ("default_value", "0"),
        ("default_speed_value", "0"),
        ("range", _fmt([low, high])),
        ("clamped", "false"),
        ("locked", "false"),
    ):
        ET.SubElement(c, tag).text = text


def _transform_axis(parent, name: str, axis: int, coordinate: str | None) -> None:
    ta = ET.SubElement(parent, "TransformAxis", name=name)
    ET.SubElement(ta, "coordinates").text = coordinate or ""
    ET.SubElement(ta, "axis").text = _fmt(np.eye(3)[axis])
    if coordinate:
        ET.SubElement(ET.SubElement(ta, "LinearFunction", name="function"), "coefficients").text = "1 0"
    else:
        ET.SubElement(ET.SubElement(ta, "Constant", name="function"), "value").text = "0"


def _spatial_transform(joint, names: list[str], order: str, translate: bool) -> None:
    """Rotations about the channel axes in order (unused rotation axes: the remaining coordinate
    axes, fixed at 0), then translations along the parent frame's X, Y, Z."""
    st = ET.SubElement(joint, "SpatialTransform")
    rot_axes = [AXIS[a] for a in order] + [a for a in range(3) if a not in [AXIS[c] for c in order]]
    for i, axis in enumerate(rot_axes[:3]):
        _transform_axis(st, f"rotation{i + 1}", axis, names[i] if i < len(order) else None)
    for i in range(3):
        _transform_axis(st, f"translation{i + 1}", i, names[len(order) + i] if translate else None)


def _offset_frame(parent, name: str, socket: str, translation, orientation) -> ET.Element:
    f = ET.SubElement(parent, "PhysicalOffsetFrame", name=name)
    ET.SubElement(f, "socket_parent").text = socket
    ET.SubElement(f, "translation").text = _fmt(translation)
    ET.SubElement(f, "orientation").text = _fmt(orientation)
    return f


def _joint(jointset, body: str, parent_socket: str, offset, orientation, names, rotational, order) -> None:
    joint = ET.SubElement(jointset, "CustomJoint", name=f"{body}_joint")
    ET.SubElement(joint, "socket_parent_frame").text = f"{body}_parent_offset"
    ET.SubElement(joint, "socket_child_frame").text = f"/bodyset/{body}"
    coords = ET.SubElement(joint, "coordinates")
    for name, rot in zip(names, rotational):
        _coordinate(coords, name, rot)
    frames = ET.SubElement(joint, "frames")
    _offset_frame(frames, f"{body}_parent_offset", parent_socket, offset, orientation)
    _spatial_transform(joint, list(names), order, translate=not all(rotational))


def _geometry(body_el, name: str, radius: float, bones) -> None:
    """A sphere at the joint and a cylinder along each bone (frames owned by the body)."""
    ET.SubElement(
        ET.SubElement(ET.SubElement(body_el, "attached_geometry"), "Sphere", name=f"{name}_joint_geom"), "radius"
    ).text = repr(radius)
    comps = None
    for i, end in enumerate(bones):
        length = float(np.linalg.norm(end))
        if length < 1e-6:
            continue
        comps = comps if comps is not None else ET.SubElement(body_el, "components")
        frame = _offset_frame(comps, f"{name}_bone{i}", "..", 0.5 * np.asarray(end), xyz_orientation(_turn_y_to(end)))
        cyl = ET.SubElement(ET.SubElement(frame, "attached_geometry"), "Cylinder", name=f"{name}_bone{i}_geom")
        ET.SubElement(cyl, "radius").text = repr(0.6 * radius)
        ET.SubElement(cyl, "half_height").text = repr(0.5 * length)


def _bones(model: Model, k: int) -> list[np.ndarray]:
    offsets = np.asarray(model.joint_offset, dtype=np.float64)
    ends = np.asarray(model.end_site_offset, dtype=np.float64).reshape(-1, 3)
    return [offsets[c] for c, p in enumerate(model.joint_parent) if p == k] + [
        ends[e] for e, j in enumerate(model.end_site_joint) if j == k
    ]


def _bodies(bodyset, character: Character, lay: Layout) -> None:
    model = character.model
    mass, com = np.asarray(model.mass, np.float64), np.asarray(model.com, np.float64)
    inertia, radii = np.asarray(model.inertia, np.float64), np.asarray(character.radii, np.float64)
    for b, name in enumerate(lay.bodies):
        i = inertia[b]
        el = ET.SubElement(bodyset, "Body", name=name)
        ET.SubElement(el, "mass").text = repr(float(mass[b]))
        ET.SubElement(el, "mass_center").text = _fmt(com[b])
        ET.SubElement(el, "inertia").text = _fmt([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]])
        k = model.body_joint[b]
        _geometry(el, name, float(max(radii[k], 1e-3)), _bones(model, k))


def model_to_osim(character: Character, name: str | None = None) -> str:
    """OpenSim 4 model XML of the character (see the module docstring for the conventions)."""
    model = character.model
    lay = layout(model)
    doc = ET.Element("OpenSimDocument", Version=OSIM_VERSION)
    root = ET.SubElement(doc, "Model", name=osim_name(name or pathlib.Path(str(character.clip.path)).stem))
    source = pathlib.Path(str(character.clip.path)).name.encode("ascii", "backslashreplace").decode()
    ET.SubElement(root, "credits").text = f"neuromotor export of {source}"
    ET.SubElement(root, "length_units").text = "meters"
    ET.SubElement(root, "force_units").text = "N"
    g_rot = ground_rotation(model.gravity)
    ET.SubElement(root, "gravity").text = _fmt(g_rot @ np.asarray(model.gravity, np.float64))
    _bodies(ET.SubElement(ET.SubElement(root, "BodySet", name="bodyset"), "objects"), character, lay)
    joints = ET.SubElement(ET.SubElement(root, "JointSet", name="jointset"), "objects")
    offsets = np.asarray(model.joint_offset, np.float64)
    for b, body in enumerate(lay.bodies):
        k, p = model.body_joint[b], model.body_parent[b]
        cols = lay.body_coordinates[b]
        names = [lay.coordinates[c] for c in cols]
        rotational = [lay.rotational[c] for c in cols]
        if p < 0:  # ground -> root: ground turned so our world's up is OpenSim's +Y
            _joint(
                joints, body, "/ground", np.zeros(3), xyz_orientation(g_rot), names, rotational, model.joint_order[k]
            )
        else:
            _joint(
                joints,
                body,
                f"/bodyset/{lay.bodies[p]}",
                offsets[k],
                np.zeros(3),
                names,
                rotational,
                model.joint_order[k],
            )
    ET.indent(doc)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(doc, encoding="unicode") + "\n"


def export_osim(character: Character, path, **kwargs) -> pathlib.Path:
    """Write :func:`model_to_osim` to ``path`` atomically."""
    text = model_to_osim(character, **kwargs)
    return atomic_write(path, lambda fh: fh.write(text))


# ----------------------------------------------------------------------------------------------
# Storage files (.mot, .sto)
# ----------------------------------------------------------------------------------------------


def storage_text(name: str, labels, time, values, in_degrees: bool) -> str:
    """An OpenSim storage file: the header, then ``time`` and one column per label (tabs)."""
    time = np.asarray(time, dtype=np.float64).reshape(-1)
    values = np.asarray(values, dtype=np.float64).reshape(len(time), -1)
    labels = list(labels)
    if values.shape[1] != len(labels):
        raise ValueError(f"{len(labels)} labels for {values.shape[1]} columns")
    head = [
        name,
        "version=1",
        f"nRows={len(time)}",
        f"nColumns={len(labels) + 1}",
        f"inDegrees={'yes' if in_degrees else 'no'}",
        "endheader",
        "\t".join(["time", *labels]),
    ]
    rows = ["\t".join(repr(float(x)) for x in row) for row in np.column_stack([time, values])]
    return "\n".join(head + rows) + "\n"


def write_storage(path, name: str, labels, time, values, in_degrees: bool = False) -> pathlib.Path:
    """Write :func:`storage_text` to ``path`` atomically."""
    text = storage_text(name, labels, time, values, in_degrees)
    return atomic_write(path, lambda fh: fh.write(text))


def _body_dofs(model: Model) -> list[tuple[int, ...]]:
    """Per body, the columns of its simulated DOFs (in channel order) in ``model.dof_names``."""
    return [tuple(sorted(model.dofs_of_body(b), key=lambda i: model.dof_slot[i])) for b in range(model.n_bodies)]


def body_rotations(model: Model, root_rot, theta_sim) -> np.ndarray:
    """(T, B, 3, 3) world rotations of the bodies from the root's and the joints' angles."""
    theta_sim = np.asarray(theta_sim, dtype=np.float64)
    rots = [np.asarray(root_rot, dtype=np.float64)]
    for b, dofs in enumerate(_body_dofs(model)[1:], start=1):
        order = model.joint_order[model.body_joint[b]]
        rots.append(rots[model.body_parent[b]] @ channel_rotation(theta_sim[:, list(dofs)], order))
    return np.stack(rots, 1)


def motion_values(model: Model, root_origin, root_rot, theta_sim) -> np.ndarray:
    """(T, n) the exported model's coordinates (radians, metres; :func:`layout` order) of a
    motion: the root's channel angles of ``root_rot`` (T, 3, 3) and its joint origin
    ``root_origin`` (T, 3) in our world frame, then the simulated joint angles ``theta_sim``."""
    lay = layout(model)
    theta_sim = np.asarray(theta_sim, dtype=np.float64)
    out = np.zeros((theta_sim.shape[0], len(lay.coordinates)))
    order = model.joint_order[model.body_joint[0]]
    root_cols = lay.body_coordinates[0]
    out[:, list(root_cols[: len(order)])] = euler_angles(root_rot, order)
    out[:, list(root_cols[len(order) :])] = np.asarray(root_origin, dtype=np.float64)
    for b, dofs in enumerate(_body_dofs(model)[1:], start=1):
        out[:, list(lay.body_coordinates[b])] = theta_sim[:, list(dofs)]
    return out


def write_motion(path, model: Model, time, root_origin, root_rot, theta_sim, name: str = "motion") -> pathlib.Path:
    """A ``.mot`` of the exported model's coordinates (rotations in degrees, ``inDegrees=yes``)."""
    lay = layout(model)
    values = motion_values(model, root_origin, root_rot, theta_sim)
    values[:, np.array(lay.rotational)] = np.rad2deg(values[:, np.array(lay.rotational)])
    return write_storage(path, name, lay.coordinates, time, values, in_degrees=True)


def coordinate_forces(model: Model, root_rot, theta_sim, joint_torque_world, root_wrench) -> np.ndarray:
    """(T, n) the generalized forces of the exported model's coordinates (:func:`layout` order):
    ``h_i . T_k`` for rotation channel i of joint k, with h_i its world axis and T_k the joint's
    world torque on its child (``idyn``'s ``joint_torque_world``); for the root, the axes of
    its channels dotted with the root wrench's torque about the root joint origin, and the
    wrench's force along the world axes (``root_wrench`` = [force, torque], world)."""
    lay = layout(model)
    theta_sim = np.asarray(theta_sim, dtype=np.float64)
    torque = np.asarray(joint_torque_world, dtype=np.float64)
    wrench = np.asarray(root_wrench, dtype=np.float64)
    rots = body_rotations(model, root_rot, theta_sim)
    out = np.zeros((theta_sim.shape[0], len(lay.coordinates)))
    order = model.joint_order[model.body_joint[0]]
    root_cols = list(lay.body_coordinates[0])
    angles = euler_angles(root_rot, order)
    axes = channel_axes(np.eye(3), angles, order)
    out[:, root_cols[: len(order)]] = np.einsum("tij,tj->ti", axes, wrench[:, 3:6])
    out[:, root_cols[len(order) :]] = wrench[:, 0:3]
    for b, dofs in enumerate(_body_dofs(model)[1:], start=1):
        k = model.body_joint[b]
        axes = channel_axes(rots[:, model.body_parent[b]], theta_sim[:, list(dofs)], model.joint_order[k])
        out[:, list(lay.body_coordinates[b])] = np.einsum("tij,tj->ti", axes, torque[:, k])
    return out


def write_idyn_storage(folder, character: Character, arrays: dict) -> dict[str, pathlib.Path]:
    """``model.osim``, ``motion.mot`` (the mocap's coordinates) and ``inverse_dynamics.sto`` (their
    generalized forces) of ``neuromotor idyn``'s arrays (:func:`physics.inverse.idyn_arrays`)."""
    from neuromotor.rotations import quat_to_matrix

    folder, model = pathlib.Path(folder), character.model
    theta = np.asarray(arrays["theta"])[:, list(model.sim_dof_columns)]
    root_rot = np.asarray(quat_to_matrix(np.asarray(arrays["root_quat"], dtype=np.float64)))  # type: ignore[arg-type]  # numpy in: jnp converts it
    forces = coordinate_forces(model, root_rot, theta, arrays["joint_torque_world"], arrays["root_wrench"])
    return {
        "model": export_osim(character, folder / "model.osim"),
        "motion": write_motion(folder / "motion.mot", model, arrays["time"], arrays["root_pos"], root_rot, theta),
        "forces": write_storage(
            folder / "inverse_dynamics.sto",
            "Inverse Dynamics Generalized Forces",
            layout(model).force_labels,
            arrays["time"],
            forces,
        ),
    }


def root_pose_of_bodies(model: Model, body_pos, body_quat) -> tuple[np.ndarray, np.ndarray]:
    """(root joint origin (T, 3), root rotation (T, 3, 3)) from body COM poses (T, B, 3/4)."""
    from neuromotor.rotations import quat_to_matrix

    rot = np.asarray(quat_to_matrix(np.asarray(body_quat, dtype=np.float64)[:, 0]))  # type: ignore[arg-type]  # numpy in: jnp converts it
    origin = np.asarray(body_pos, dtype=np.float64)[:, 0] - rot @ np.asarray(model.com, np.float64)[0]
    return origin, rot


def write_run_storage(folder, character: Character, arrays: dict) -> dict[str, pathlib.Path]:
    """``model.osim``, ``perturbed.mot`` and ``unperturbed.mot`` of a simulated run's arrays
    (RUN.npz fields ``time``, ``theta``, ``body_pos``, ``body_quat`` and their twins); with the
    capture's residuals (``grf_force`` ...), the files of :func:`write_ground_storage` too."""
    folder, model = pathlib.Path(folder), character.model
    out = {"model": export_osim(character, folder / "model.osim")}
    for key, suffix in (("perturbed", ""), ("unperturbed", "_unperturbed")):
        origin, rot = root_pose_of_bodies(model, arrays["body_pos" + suffix], arrays["body_quat" + suffix])
        out[key] = write_motion(
            folder / f"{key}.mot", model, arrays["time"], origin, rot, arrays["theta" + suffix], name=key
        )
    if "grf_force" in arrays:
        out.update(write_ground_storage(folder, character, arrays))
    return out


# ----------------------------------------------------------------------------------------------
# Ground reaction forces and residuals (issue 38; neuromotor.studies.residuals)
# ----------------------------------------------------------------------------------------------

EXTERNAL_LOADS = "external_loads"  # <name>.sto (the data) and <name>.xml (OpenSim's ExternalLoads)
RESIDUALS = "residuals"  # <name>.sto


def external_load_labels(body: str) -> tuple[str, ...]:
    """The ``.sto`` columns of one body's ExternalForce: OpenSim's ``<id>x``, ``<id>y``, ``<id>z``
    for the force (``<body>_force_v``), its point (``<body>_force_p``) and the torque
    (``<body>_torque_``)."""
    return tuple(f"{body}_{kind}{a}" for kind in ("force_v", "force_p", "torque_") for a in "xyz")


def external_loads_xml(bodies, datafile: str) -> str:
    """OpenSim's ExternalLoads: one ExternalForce per body, force and point in ground."""
    doc = ET.Element("OpenSimDocument", Version=OSIM_VERSION)
    loads = ET.SubElement(doc, "ExternalLoads", name="externalloads")
    objects = ET.SubElement(loads, "objects")
    for body in bodies:
        force = ET.SubElement(objects, "ExternalForce", name=f"{body}_ground")
        for tag, text in (
            ("applied_to_body", body),
            ("force_expressed_in_body", "ground"),
            ("point_expressed_in_body", "ground"),
            ("force_identifier", f"{body}_force_v"),
            ("point_identifier", f"{body}_force_p"),
            ("torque_identifier", f"{body}_torque_"),
        ):
            ET.SubElement(force, tag).text = text
    ET.SubElement(loads, "datafile").text = datafile
    ET.indent(doc)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(doc, encoding="unicode") + "\n"


def write_ground_storage(folder, character: Character, arrays: dict) -> dict[str, pathlib.Path]:
    """``external_loads.sto`` and ``external_loads.xml`` (the ground reaction forces of the
    capture's contact-aware inverse dynamics as OpenSim ExternalForces on their bodies: force,
    centre of pressure, free torque) and ``residuals.sto`` (the root force and moment they leave,
    the moment about the whole body's COM, and that point: ``residual_force_x`` ...,
    ``residual_moment_x`` ..., ``residual_point_x`` ...). In OpenSim's ground frame (our world
    turned by :func:`ground_rotation`); N, N m, m."""
    folder, model = pathlib.Path(folder), character.model
    turn = ground_rotation(model.gravity)
    ground = lambda a: np.einsum("ij,...j->...i", turn, np.asarray(a, np.float64))
    names = [layout(model).bodies[int(b)] for b in np.asarray(arrays["grf_body"])]
    time = arrays["time"]
    parts = [ground(arrays[f"grf_{k}"]) for k in ("force", "point", "torque")]  # (T, K, 3) each
    values = np.stack(parts, 2).reshape(len(time), -1)  # per body: force, point, torque
    labels = [c for body in names for c in external_load_labels(body)]
    data = write_storage(folder / f"{EXTERNAL_LOADS}.sto", "ExternalLoads", labels, time, values)
    text = external_loads_xml(names, data.name)
    setup = atomic_write(folder / f"{EXTERNAL_LOADS}.xml", lambda fh: fh.write(text))
    kinds = ("force", "moment", "point")
    res = np.concatenate([ground(arrays[f"residual_{k}"]) for k in kinds], -1)
    res_labels = [f"residual_{k}_{a}" for k in kinds for a in "xyz"]
    residuals = write_storage(folder / f"{RESIDUALS}.sto", "Residuals", res_labels, time, res)
    return {"external_loads": data, "external_loads_setup": setup, "residuals": residuals}
