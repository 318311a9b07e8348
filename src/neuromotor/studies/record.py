"""What a run records: the arrays of RUN.npz computed from a simulation, and its provenance.

The file format (field names, shapes, reading, checking, writing) is
:mod:`neuromotor.io.runfile`; this module turns a :class:`~neuromotor.studies.simulate.Setup` and
its :class:`~neuromotor.studies.simulate.RunResult` into those arrays: skeleton points from the
simulated body poses (joint frames of massless joints from the mocap), body shapes for drawing,
the facing direction, and the JSON of metrics and provenance.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import pathlib
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from neuromotor import compiler
from neuromotor.model.facing import facing_direction
from neuromotor.model.kinematics import Trajectory, body_poses, local_rotations, skeleton_edges, skeleton_points
from neuromotor.model.skeleton import Model
from neuromotor.rotations import continuous_angles, quat_to_matrix
from neuromotor.studies import metrics as mx

if TYPE_CHECKING:
    from neuromotor.physics.dynamics import Rollout
    from neuromotor.studies.simulate import RunResult, Setup


def up_axis_of(model: Model) -> int:
    """The coordinate axis gravity pulls against (0, 1 or 2)."""
    return int(np.argmax(np.abs(np.asarray(model.gravity))))


# ----------------------------------------------------------------------------------------------
# Skeleton points of simulated states
# ----------------------------------------------------------------------------------------------


def joint_frames_from_state(model: Model, pos, rot, local_ref):
    """World origin and rotation of every joint: bodies from the state, massless joints from
    their parent frame and the mocap's local rotations ``local_ref`` (J, 3, 3)."""
    joint_body = np.array(model.joint_body)
    carried = np.flatnonzero(joint_body >= 0)
    b = joint_body[carried]
    origins = pos[b] - jnp.einsum("bij,bj->bi", rot[b], model.com[b])
    rots = rot[b]
    if len(carried) == len(joint_body):  # every joint carries a body
        return origins, rots
    n = len(joint_body)
    origins = jnp.zeros((n, 3), pos.dtype).at[carried].set(origins)
    rots = jnp.zeros((n, 3, 3), rot.dtype).at[carried].set(rots)
    # Massless joints (leaves and their chains) one tree level at a time, parents first.
    parent = np.array(model.joint_parent)
    depth = model.topology.joint_depth
    for d in np.unique(depth[joint_body < 0]):
        k = np.flatnonzero((joint_body < 0) & (depth == d))
        p = parent[k]
        origins = origins.at[k].set(origins[p] + jnp.einsum("kij,kj->ki", rots[p], model.joint_offset[k]))
        rots = rots.at[k].set(rots[p] @ local_ref[k])
    return origins, rots


@compiler.jit
def _skeleton_points(model: Model, traj: Trajectory, time, pos, quat):
    """Skeleton points of states (leading time axis), as one compiled program."""

    def one(pos, quat, qr):
        o, r = joint_frames_from_state(model, pos, quat_to_matrix(quat), local_rotations(model, qr))
        return skeleton_points(model, o, r)

    return jax.vmap(one)(pos, quat, jax.vmap(traj.q)(time))


def rollout_points(setup: Setup, run_: Rollout) -> np.ndarray:
    """(S+1, P, 3) skeleton points (joints then End Sites) of a rollout, for drawing."""
    return np.asarray(_skeleton_points(setup.model, setup.traj, run_.time, run_.states.pos, run_.states.quat))


# ----------------------------------------------------------------------------------------------
# RUN.npz arrays
# ----------------------------------------------------------------------------------------------


@functools.partial(compiler.jit, static_argnames=("metric",))
def _deviation(metric: str, model: Model, pert, base):
    return mx.run_deviation(metric, model, pert, base)


def _motion_arrays(setup: Setup, result: RunResult) -> dict[str, np.ndarray]:
    """Time, joint angles, body poses, the deviation d(t) of the run's metrics, the applied
    force and the solver's diagnostics."""
    model = setup.model
    pert, base = result.perturbed, result.unperturbed
    force = np.asarray(pert.force)
    total = force.sum(axis=1)
    pts = np.asarray(pert.points)
    origin = pts[:, 0, :] if pts.shape[1] else np.zeros_like(total)
    # Continuous angles (no 2 pi jumps in time), on the mocap's branch at the start: what
    # export-bvh writes and what a plot of theta against time should show.
    theta_desired = np.asarray(setup.ref.theta)[: pert.time.shape[0]]
    theta_base = continuous_angles(np.asarray(base.theta), theta_desired)
    return {
        "time": np.asarray(pert.time),
        "dof_names": np.array(model.dof_names),
        "theta": continuous_angles(np.asarray(pert.theta), theta_base),
        "theta_unperturbed": theta_base,
        "theta_desired": theta_desired,
        # d(t) as the metrics measured it ([sim] metric), so plots and the viewer draw that curve
        "deviation": np.asarray(_deviation(setup.config.metric, model, pert, base)),
        "deviation_metric": np.asarray(setup.config.metric),
        "body_names": np.array(model.body_names),
        "body_pos": np.asarray(pert.states.pos),
        "body_quat": np.asarray(pert.states.quat),
        "body_pos_unperturbed": np.asarray(base.states.pos),
        "body_quat_unperturbed": np.asarray(base.states.quat),
        "perturbation_force": force,
        "force_origin": origin,
        "force_vector": total,
        "kkt_residual": np.asarray(pert.residual),
        "constraint_violation": np.asarray(pert.violation),
    }


def _skeleton_arrays(setup: Setup, result: RunResult) -> dict[str, np.ndarray]:
    """Skeleton points of both runs, the bones, their radii and the body carrying each bone."""
    model = setup.model
    edges = skeleton_edges(model)
    return {
        "skeleton_points": rollout_points(setup, result.perturbed),
        "skeleton_points_unperturbed": rollout_points(setup, result.unperturbed),
        "skeleton_edges": edges,
        "skeleton_radii": np.asarray(setup.character.radii)[skeleton_edges(model)[:, 0]],
        # Body whose shape carries each drawn bone (its parent joint's body), -1 for detail bones.
        "skeleton_edge_body": np.asarray(model.joint_body, dtype=np.int64)[edges[:, 0]],
    }


def _source_arrays(setup: Setup, result: RunResult) -> dict[str, np.ndarray]:
    """Where the run came from: up axis, clip, units, window start, metrics and provenance."""
    clip = setup.character.clip
    return {
        "up_axis": np.asarray(up_axis_of(setup.model)),
        "source_clip": np.asarray(str(pathlib.Path(clip.path).resolve())),
        "source_units": np.asarray(repr(float(clip.length_scale))),
        "clip_start": np.asarray(setup.config.start),
        **({} if setup.config.still is None else {"clip_still": np.asarray(float(setup.config.still))}),
        "metrics_json": np.asarray(json.dumps(result.metrics)),
        "provenance_json": np.asarray(json.dumps(provenance(setup), default=_json_default)),
    }


def shape_arrays(setup: Setup) -> dict[str, np.ndarray]:
    """Body shapes for drawing: every body's polyhedron in its body frame less its COM, so that
    a vertex v of body b is at ``body_pos[:, b] + R(body_quat[:, b]) @ v`` in the world."""
    com = np.asarray(setup.model.com)
    verts, faces, owner, n_v = [], [], [], 0
    for b, shape in enumerate(setup.character.shapes):
        if shape is None:
            continue
        v = np.asarray(shape.vertices, dtype=np.float64)
        verts.append(v - com[b])
        faces.append(np.asarray(shape.faces, dtype=np.int64) + n_v)
        owner.append(np.full(len(v), b, dtype=np.int64))
        n_v += len(v)
    return {
        "shape_vertices": np.concatenate(verts) if verts else np.zeros((0, 3)),
        "shape_faces": np.concatenate(faces) if faces else np.zeros((0, 3), np.int64),
        "shape_body": np.concatenate(owner) if owner else np.zeros(0, np.int64),
    }


def anatomy_forward(setup: Setup, base_quat) -> np.ndarray | None:
    """The anatomy's forward direction (a world direction at the clip's reference frame) carried
    with the root body over the simulated window ``base_quat`` (T, B, 4) and averaged; None when
    the character's anatomy has no usable forward."""
    anatomy = getattr(setup.character, "anatomy", None)
    forward = getattr(anatomy, "forward", None)
    if forward is None:
        return None
    try:
        forward = np.asarray(forward, dtype=np.float64).reshape(3)
        ref_frame = getattr(anatomy, "reference_frame", None)
        if ref_frame is not None:
            t_ref = jnp.asarray(float(ref_frame) * setup.character.clip.frame_time)
            _, rot_ref = body_poses(setup.model, setup.clip_trajectory.q(t_ref))
            local = np.asarray(rot_ref)[0].T @ forward
            forward = np.asarray((quat_to_matrix(jnp.asarray(base_quat[:, 0])) @ local).mean(axis=0))
    except Exception:  # an anatomy without a usable forward: the skeleton estimate
        return None
    return forward


def residual_part(setup: Setup, n_times: int) -> dict[str, np.ndarray]:
    """The capture's residuals with the ground (issue 38, :mod:`neuromotor.studies.residuals`),
    for a reference made by the discrete inverse (its velocities); none with Eq. 3's."""
    if setup.ref.velocity is None:
        return {}
    from neuromotor.studies.residuals import capture_residuals, residual_arrays

    # One floor and one friction coefficient in the file: the simulated ground's where the run has one.
    ground = setup.ground
    floor = None if ground is None else float(ground.height)
    mu = {} if ground is None else {"mu": float(ground.friction)}
    res = capture_residuals(
        setup.character, setup.traj, setup.ref, setup.options, floor, capture=setup.clip_trajectory, **mu
    )
    return {k: v if v.ndim == 0 or k == "grf_body" else v[:n_times] for k, v in residual_arrays(res).items()}


def run_arrays(setup: Setup, result: RunResult, residuals: bool | None = None) -> dict[str, np.ndarray]:
    """The arrays of RUN.npz (the contract of :mod:`neuromotor.io.runfile`), the ball's included
    when the run has one; the capture's residuals with the ground (:func:`residual_part`) when
    ``residuals``, by default when the run has a ground (a second inverse problem per step, so
    not for every driven run: ``neuromotor simulate --residuals`` asks for it)."""
    arrays = {
        **_motion_arrays(setup, result),
        **_skeleton_arrays(setup, result),
        **_source_arrays(setup, result),
        **shape_arrays(setup),
    }
    if residuals if residuals is not None else setup.ground is not None:
        arrays.update(residual_part(setup, arrays["time"].shape[0]))
    # Horizontal facing direction: the anatomy's forward, else estimated from the skeleton.
    forward = anatomy_forward(setup, result.unperturbed.states.quat)
    arrays["facing"] = facing_direction(
        arrays["skeleton_points_unperturbed"], arrays["skeleton_edges"], int(arrays["up_axis"]), forward
    )
    if setup.pulses.base_offset is not None:  # the driven root's added path (world, m): the sled's
        arrays["base_offset"] = np.asarray(setup.pulses.base_offset)[: arrays["time"].shape[0]]
    if setup.pulses.base_turn is not None:  # a tilted ground: its orientation per sample, its pivot
        arrays["ground_turn"] = np.asarray(setup.pulses.base_turn)[: arrays["time"].shape[0]]
        arrays["ground_pivot"] = np.asarray(setup.pulses.base_pivot)
    if getattr(result, "ball", None) is not None:
        from neuromotor.studies.ball_hit import ball_arrays

        arrays.update(ball_arrays(setup, result))
    if getattr(setup.gains, "balance", None) is not None:  # the assist, when on: help, not physics
        from neuromotor.studies.balance import assist_forces

        states = result.perturbed.states
        root_pos, root_vel = np.asarray(states.pos[:, 0]), np.asarray(states.vel[:, 0])
        pulses = setup.pulses
        assist = assist_forces(setup, root_pos, root_vel, pulses.base_offset, pulses.base_velocity)
        if assist is not None:
            arrays["assist_force"], arrays["assist_point"] = assist, root_pos
    contact = result.ball if getattr(result, "ball", None) is not None else getattr(result, "ground", None)
    if getattr(setup, "ground", None) is not None and contact is not None:
        from neuromotor.studies.ground import ground_arrays

        arrays.update(ground_arrays(setup, contact))
    return arrays


# ----------------------------------------------------------------------------------------------
# Provenance
# ----------------------------------------------------------------------------------------------


def file_sha256(path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _json_default(obj):
    if isinstance(obj, (np.ndarray, jax.Array)):
        return np.asarray(obj).tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, pathlib.Path):
        return str(obj)
    return repr(obj)


def _floats(a):
    a = np.asarray(a, dtype=np.float64)
    return a.tolist()


def _perturbation_records(setup: Setup) -> list[dict]:
    """Each perturbation as configured (an impulse in N s, not the one-step pulse the step
    applies), with its resolved body, point and world direction; a base motion with its unit,
    its file and the span it acts over."""

    p, names = setup.pulses, setup.model.body_names
    direction_of = setup.direction_of
    perts, row = [], 0
    for spec in setup.config.perturbations:
        common = {
            "kind": spec.kind,
            "magnitude": float(spec.magnitude or 0.0),
            "unit": spec.magnitude_unit,
            "start": float(spec.start),
            "duration": float(spec.span),  # an impulse: 0 (it acts within one step)
            "shape": spec.shape if spec.reads(spec.kind, "shape") and not spec.recorded else None,
        }
        if spec.kind == "tilt":  # the axis as used, the pivot as used
            axis = direction_of(spec.direction, float(spec.start))
            assert p.base_pivot is not None
            perts.append(
                {
                    **common,
                    "direction": _floats(axis),
                    "direction_given": spec.direction,
                    "pivot": _floats(np.asarray(p.base_pivot)),
                    "pivot_given": spec.pivot is not None,
                }
            )
            continue
        if spec.kind == "base":
            direction = direction_of(spec.direction, float(spec.start))
            acting = spec.acting(setup.options.h)
            extra = {"file": spec.file, "acting": [float(acting[0]), float(acting[1])]} if spec.recorded else {}
            perts.append({**common, "direction": _floats(direction), "direction_given": spec.direction, **extra})
            continue
        b = int(np.asarray(p.body)[row])
        perts.append(
            {
                **common,
                "body_requested": spec.body,
                "body": names[b],
                "body_index": b,
                "point": _floats(np.asarray(p.point)[row]),
                "point_given": spec.point is not None,
                "direction": _floats(np.asarray(p.direction)[row]),
                "direction_given": spec.direction,
            }
        )
        row += 1
    return perts


def _ground_record(setup: Setup) -> dict | None:
    """The ground the bodies touch (its resolved height), or None."""
    g = getattr(setup, "ground", None)
    if g is None:
        return None
    return {
        "height": float(g.height),
        "friction": float(g.friction),
        "restitution": float(g.restitution),
        "contacts_per_body": int(g.per_body),
        "max_contacts": int(g.max_contacts),
        "pgs_iterations": int(g.pgs_iterations),
        # Each body's forward and left axes in its own frame: its friction polygon's orientation.
        "friction_axes": np.asarray(g.axes, np.float64).tolist(),
    }


def _balance_record(setup: Setup) -> dict | None:
    """The postural loop as it ran (docs/balance.md): its gains and delay, the assist, the
    history's length, stepping on or off, and the feet and hips by name; None without it."""
    bal = setup.gains.balance
    if bal is None:
        return None
    model, h = setup.model, setup.options.h
    out = {k: float(getattr(bal, k)) for k in ("kp", "kd", "hip_kp", "hip_kd", "delay", "assist")}
    return out | {
        "longest_delay": float((bal.steps - 1) * h),  # s: what its history holds (raise max_delay for more)
        "stepping": bal.stepping is not None,
        "feet": [model.body_names[b] for b in bal.feet],
        "hips": [model.body_names[c + 1] for c in bal.hips],  # joint c attaches body c + 1
        "mgh_Nm_per_rad": float(bal.mgh),
        "com_height_m": float(bal.height),
    }


def _ball_record(setup: Setup) -> dict | None:
    """The ball's configuration and resolved parameters, or None without a ball."""
    cfg = setup.config
    if setup.ball is not None:
        b = setup.ball.ball
        assert cfg.ball is not None  # the setup has a ball
        ball = {"config": dict(cfg.ball)}
        ball.update({f.name: _floats(getattr(b, f.name)) for f in dataclasses.fields(b)})
        return ball
    return {"config": dict(cfg.ball)} if cfg.ball else None


def _clip_record(setup: Setup) -> dict:
    """The clip file, its SHA-256 and its frames."""
    clip = setup.character.source
    clip_path = pathlib.Path(clip.path).resolve()
    return {
        "path": str(clip_path),
        "sha256": file_sha256(clip_path) if clip_path.is_file() else None,
        "frames": int(clip.n_frames),
        "frame_time": float(clip.frame_time),
    }


def _body_record(setup: Setup) -> dict:
    """Units, up axis, stature and mass as requested and as resolved."""
    cfg, model, character = setup.config, setup.model, setup.character
    anat = getattr(character, "anatomy", None)
    return {
        "units": {
            "requested": cfg.units,
            "resolved": getattr(anat, "units", None),
            "length_scale": float(character.clip.length_scale),
        },
        "up_axis": {
            "requested": cfg.up_axis,
            "resolved": up_axis_of(model),
            "up": _floats(anat.up) if anat is not None else None,
        },
        "stature": {"requested": cfg.stature, "resolved": float(anat.stature) if anat is not None else None},
        "body_mass": {"requested": cfg.body_mass, "total": float(np.sum(np.asarray(model.mass)))},
        "sex": cfg.sex,
        "simulate_extremities": bool(cfg.simulate_extremities),
        "n_bodies": int(model.n_bodies),
        "n_dofs": int(model.n_dofs),
    }


def provenance(setup: Setup) -> dict:
    """What made a run, as plain JSON values (RUN.npz ``provenance_json``): the package
    version, the clip file and its SHA-256, and the fully resolved configuration (gains, step,
    window, perturbations with their resolved body and point, units, up axis, stature, mass
    options, ground, ball, delayed reflex, postural loop)."""
    from neuromotor import __version__

    cfg, options = setup.config, setup.options
    return {
        "neuromotor_version": __version__,
        "jax_version": jax.__version__,
        "config_source": cfg.source,
        "clip": _clip_record(setup),
        "gains": {"ks": float(cfg.ks), "kd": float(cfg.kd), "tau_floor": float(cfg.tau_floor)},
        "h": float(cfg.h),
        "start": float(cfg.start),
        "duration": float(options.n_steps * cfg.h),
        "n_steps": int(options.n_steps),
        "implicit": bool(cfg.implicit),
        "stabilization_steps": int(cfg.stabilization_steps),
        "dtype": str(cfg.dtype),  # float64, or float32 (docs/float32.md)
        "still": None if cfg.still is None else float(cfg.still),  # clip time of a held pose ([sim] still)
        # The driven bodies by name (keywords such as "trunk" resolved), and the entries as given.
        "driven_joints": [setup.model.body_names[b] for b in options.driven],
        "driven_joints_requested": list(cfg.driven_joints),
        "root": "free" if options.free_root else "driven",
        "ground": _ground_record(setup),
        "perturbations": _perturbation_records(setup),
        "ball": _ball_record(setup),
        # The postural loop (docs/balance.md), or None: a driven root, or the loop off.
        "balance": _balance_record(setup),
        # The delayed reflex (docs/reflex.md), or None: the paper's controller.
        "reflex": None if cfg.reflex is None else dataclasses.asdict(cfg.reflex),
        **_body_record(setup),
    }
