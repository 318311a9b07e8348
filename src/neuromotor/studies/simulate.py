"""The end-to-end pipeline: clip -> model -> inverse dynamics -> perturbed and unperturbed rollouts.

    setup = prepare(SimulationConfig())          # embedded clip, default gains, no hit
    result = run(setup)
    result.metrics["peak_deviation_deg"]
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from neuromotor import compiler

from neuromotor.physics import contact
from neuromotor.studies import metrics as mx
from neuromotor.io.atomic import atomic_path
from neuromotor.model.bvh import BvhClip
from neuromotor.config import ConfigError, SimulationConfig
from neuromotor.physics.control import Gains, make_gains
from neuromotor.physics.dynamics import Reference, Rollout, SimConfig, check_rollout, make_reference, rollout
from neuromotor.model.kinematics import (Trajectory, local_rotations, skeleton_edges, skeleton_points, structure,
                         trajectory_from_clip)
from neuromotor.physics.perturbation import ForcePulses, pulses
from neuromotor.rotations import quat_to_matrix
from neuromotor.model.anatomy import prepare_clip
from neuromotor.model.skeleton import BODY_KEYWORDS, Character, MassModelOptions, Model, build_character, keyword_body

DEFAULT_CLIP_NAME = "mocapbank_19joint.bvh"


def default_clip_path() -> pathlib.Path:
    """Path of the embedded default clip (MocapBank capture, MIT; see data/README.md)."""
    return pathlib.Path(str(importlib.resources.files("neuromotor") / "data" / DEFAULT_CLIP_NAME))


def load_character(path=None, units="auto", up_axis: int | None = None, stature: float | None = None,
                   options: MassModelOptions | None = None) -> tuple[Character, Trajectory]:
    """Read a clip, understand its skeleton (units, up axis, segments, a virtual root) and build
    the character and its mocap trajectory. ``up_axis`` None: found from the motion."""
    clip, anatomy, source = prepare_clip(path or default_clip_path(), units=units, stature=stature)
    character = build_character(clip, options, up_axis=up_axis, anatomy=anatomy, source_clip=source)
    return character, trajectory_from_clip(character.model, clip)


@dataclasses.dataclass
class Setup:
    """Everything a rollout needs; ``model``, ``gains``, ``pulses`` and ``ref`` are pytrees."""

    character: Character
    traj: Trajectory
    ref: Reference
    gains: Gains
    sim: SimConfig
    pulses: ForcePulses
    config: SimulationConfig
    ball: "contact.BallSetup | None" = None  # a [ball] config: the flying ball and its contacts
    warnings: tuple[str, ...] = ()  # the clip's (see Character.warnings) and the run's, one line each

    @property
    def model(self) -> Model:
        return self.character.model


# The driven root turning more than this per step (rad) makes the replay drift by degrees: the
# step integrates every body's rotation in the world frame, with an error that grows with the
# rotation per step (the Bandai-Namco kick spins at 11 rad/s: 1.97 deg RMS at h = 1/120 s,
# 0.72 deg at 1/360 s; docs/body-model.md).
MAX_ROOT_TURN_PER_STEP = 0.05


def step_warnings(ref: Reference, h: float) -> tuple[str, ...]:
    """A warning when the driven root turns faster than the time step follows well."""
    omega = float(np.max(np.linalg.norm(np.asarray(ref.root_omega), axis=-1)))
    if omega * h <= MAX_ROOT_TURN_PER_STEP:
        return ()
    h_good = MAX_ROOT_TURN_PER_STEP / omega
    return (f"the root turns at up to {omega:.1f} rad/s, {omega * h:.3f} rad per step of h = {h:.4g} s: the "
            f"replay may drift by degrees; sim.h <= {h_good:.4g} s keeps it within about a degree",)


def body_lookup(model: Model, source: str = "config", character: Character | None = None):
    """Name -> body index: a body (joint) name, or a segment keyword such as ``chest``."""
    def index(name: str) -> int:
        if name in model.body_names:
            return model.body_names.index(name)
        b = keyword_body(character, name) if character is not None else None
        if b is None:
            raise ConfigError(f"{source}: unknown body {name!r}; bodies are {', '.join(model.body_names)}"
                              f" (or one of {', '.join(BODY_KEYWORDS)})")
        return b

    return index


def prepare(config: SimulationConfig, character: Character | None = None,
            traj: Trajectory | None = None) -> Setup:
    if character is None:
        character, traj = load_character(config.clip, config.units, config.up_axis, config.stature,
                                         config.mass_options())
    model, clip = character.model, character.clip
    duration = clip.duration - config.start if config.duration is None else config.duration
    if config.start + duration > clip.duration + 1e-9:
        raise ConfigError(f"{config.source}: sim.start + sim.duration = {config.start + duration:.3f} s "
                          f"runs past the clip's end ({clip.duration:.3f} s)")
    n_steps = int(round(duration / config.h))
    if n_steps < 1:
        raise ConfigError(f"{config.source}: sim.duration is shorter than one step")
    # A perturbation (or ball launch) that never acts inside the simulated window [t0, t1) would
    # give a run of zeros ('peak 0.00 deg') that looks like a result: refuse it, naming the field.
    t0, t1 = config.start, config.start + n_steps * config.h
    window = f"the simulated window {t0:.3f} to {t1:.3f} s (the clip ends at {clip.duration:.3f} s)"
    for i, p in enumerate(config.perturbations):
        p_start, impulse = float(p.get("start", 0.5)), p.get("kind") == "impulse"
        p_end = p_start + (0.5 * config.h if impulse else float(p.get("duration", 0.1)))  # impulse: centred
        if p_start >= t1 - 1e-9:
            raise ConfigError(f"{config.source}: field 'perturbation[{i}].start' = {p_start:g} s is at or "
                              f"after the end of {window}")
        if p_end <= t0:
            raise ConfigError(f"{config.source}: field 'perturbation[{i}].start' = {p_start:g} s: the "
                              f"perturbation is over before {window} begins")
    if config.ball is not None and float(config.ball.get("launch", 0.0)) >= t1 - 1e-9:
        raise ConfigError(f"{config.source}: field 'ball.launch' = {float(config.ball['launch']):g} s is at "
                          f"or after the end of {window}")
    index = body_lookup(model, config.source, character)
    driven = []
    for name in config.driven_joints:
        b = index(name)
        if b == 0:
            raise ConfigError(f"{config.source}: sim.driven_joints: the root is always driven")
        driven.append(b)
    driven = tuple(sorted(driven))
    ref = make_reference(model, traj, config.start, config.h, n_steps)
    gains = _initial_gains(model, traj, jnp.asarray(config.start), ref.theta, ref.activation,
                           config.ks, config.kd, config.tau_floor)
    sim = SimConfig(h=config.h, n_steps=n_steps, driven=driven, implicit=config.implicit,
                    stab_iters=config.stabilization_steps)
    # An impulse is a one-step square pulse: it needs the step to know its force.
    specs = [dict(p, step=config.h) for p in config.perturbations]
    for s in specs:  # no point given: push at the body's centre of mass
        if s.get("point") is None:
            s["point"] = [float(x) for x in np.asarray(model.com[index(s["body"])])]
    ball = contact.ball_setup(config.ball, character, traj, index, config.source) if config.ball else None
    warnings = tuple(character.warnings) + step_warnings(ref, config.h)
    return Setup(character, traj, ref, gains, sim, pulses(specs, index), config, ball, warnings)


@jax.jit
def _initial_gains(model: Model, traj: Trajectory, t0, theta, activation, ks, kd, tau_floor) -> Gains:
    """:func:`make_gains` at the clip's start, the spline evaluation included: one program
    rather than a dozen eagerly compiled scalar ops."""
    return make_gains(model, traj.q(t0), theta[0], activation, ks, kd, tau_floor)


@jax.jit
def _zero(p: ForcePulses) -> ForcePulses:
    return dataclasses.replace(p, magnitude=jnp.zeros_like(p.magnitude))


simulate_jit = compiler.jit(rollout, static_argnames=("cfg",))


@dataclasses.dataclass
class RunResult:
    perturbed: Rollout
    unperturbed: Rollout
    metrics: dict
    ball: "contact.ContactRollout | None" = None


def run(setup: Setup, check: bool = True) -> RunResult:
    """Perturbed and unperturbed rollouts plus the recovery metrics."""
    if setup.ball is not None:
        return contact.run_ball(setup, check)
    model = setup.model
    pert = simulate_jit(model, setup.gains, setup.pulses, setup.ref, setup.sim)
    base = simulate_jit(model, setup.gains, _zero(setup.pulses), setup.ref, setup.sim)
    if check:
        check_rollout(model, base)
        check_rollout(model, pert)
    return RunResult(pert, base, run_metrics(setup, pert, base))


def run_metrics(setup: Setup, pert: Rollout, base: Rollout) -> dict:
    starts = [p["start"] for p in setup.config.perturbations]
    if setup.ball is not None:
        starts.append(float(setup.ball.ball.launch))
    start = min(starts, default=float(np.asarray(setup.ref.time)[0]))
    dev, residual, violation = _metric_arrays(pert.theta, base.theta, pert.residual, base.residual,
                                              pert.violation, base.violation)
    out = mx.recovery_metrics(pert.time, dev, start)
    out["unperturbed_rms_error_deg"] = mx.rms_error_deg(base.theta, setup.ref.theta)
    out["max_kkt_residual"] = float(residual)
    out["max_constraint_violation"] = float(violation)
    out["diverged"] = bool(int(pert.diverged_step) >= 0 or int(base.diverged_step) >= 0)
    return out


@jax.jit
def _metric_arrays(theta, theta_base, residual, residual_base, violation, violation_base):
    """The array reductions of :func:`run_metrics` as one program (not a dozen eager ops)."""
    return (mx.deviation(theta, theta_base), jnp.maximum(jnp.max(residual), jnp.max(residual_base)),
            jnp.maximum(jnp.max(violation), jnp.max(violation_base)))


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
    depth = structure(model)["depth"]
    for d in np.unique(depth[joint_body < 0]):
        k = np.flatnonzero((joint_body < 0) & (depth == d))
        p = parent[k]
        origins = origins.at[k].set(origins[p] + jnp.einsum("kij,kj->ki", rots[p], model.joint_offset[k]))
        rots = rots.at[k].set(rots[p] @ local_ref[k])
    return origins, rots


@jax.jit
def _skeleton_points(model: Model, traj: Trajectory, time, pos, quat):
    """Skeleton points of states (leading time axis), as one compiled program."""
    def one(pos, quat, qr):
        o, r = joint_frames_from_state(model, pos, quat_to_matrix(quat), local_rotations(model, qr))
        return skeleton_points(model, o, r)

    return jax.vmap(one)(pos, quat, jax.vmap(traj.q)(time))


def rollout_points(setup: Setup, run_: Rollout) -> np.ndarray:
    """(S+1, P, 3) skeleton points (joints then End Sites) of a rollout, for drawing."""
    return np.asarray(_skeleton_points(setup.model, setup.traj, run_.time, run_.states.pos, run_.states.quat))


def run_arrays(setup: Setup, result: RunResult) -> dict[str, np.ndarray]:
    """The RUN.npz contract (see README)."""
    model = setup.model
    pert, base = result.perturbed, result.unperturbed
    force = np.asarray(pert.force)
    total = force.sum(axis=1)
    pts = np.asarray(pert.points)
    origin = pts[:, 0, :] if pts.shape[1] else np.zeros_like(total)
    clip = setup.character.clip
    # Continuous angles (no 2 pi jumps in time), on the mocap's branch at the start: what
    # export-bvh writes and what a plot of theta against time should show.
    theta_desired = np.asarray(setup.ref.theta)[: pert.time.shape[0]]
    theta_base = mx.continuous_angles(np.asarray(base.theta), theta_desired)
    arrays = {
        "time": np.asarray(pert.time),
        "dof_names": np.array(model.dof_names),
        "theta": mx.continuous_angles(np.asarray(pert.theta), theta_base),
        "theta_unperturbed": theta_base,
        "theta_desired": theta_desired,
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
        "skeleton_points": rollout_points(setup, pert),
        "skeleton_points_unperturbed": rollout_points(setup, base),
        "skeleton_edges": skeleton_edges(model),
        "skeleton_radii": np.asarray(setup.character.radii)[skeleton_edges(model)[:, 0]],
        "up_axis": np.asarray(up_axis_of(model)),
        "source_clip": np.asarray(str(pathlib.Path(clip.path).resolve())),
        "source_units": np.asarray(repr(float(clip.length_scale))),
        "clip_start": np.asarray(setup.config.start),
        "metrics_json": np.asarray(json.dumps(result.metrics)),
        "provenance_json": np.asarray(json.dumps(provenance(setup), default=_json_default)),
    }
    # Body shapes for drawing: every body's polyhedron in its body frame less its COM, so that a
    # vertex v of body b is at body_pos[:, b] + R(body_quat[:, b]) @ v in the world.
    com = np.asarray(model.com)
    verts, faces, owner, n_v = [], [], [], 0
    for b, shape in enumerate(setup.character.shapes):
        if shape is None:
            continue
        v = np.asarray(shape.vertices, dtype=np.float64)
        verts.append(v - com[b])
        faces.append(np.asarray(shape.faces, dtype=np.int64) + n_v)
        owner.append(np.full(len(v), b, dtype=np.int64))
        n_v += len(v)
    arrays["shape_vertices"] = np.concatenate(verts) if verts else np.zeros((0, 3))
    arrays["shape_faces"] = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
    arrays["shape_body"] = np.concatenate(owner) if owner else np.zeros(0, np.int64)
    # Body whose shape carries each drawn bone (its parent joint's body), -1 for detail bones.
    arrays["skeleton_edge_body"] = np.asarray(model.joint_body, dtype=np.int64)[arrays["skeleton_edges"][:, 0]]
    # Horizontal facing direction: the anatomy's forward (a world direction at the clip's
    # reference frame), carried with the root body to the simulated window; else estimated from
    # the skeleton.
    from neuromotor.viz.render import facing_direction

    forward = getattr(getattr(setup.character, "anatomy", None), "forward", None)
    if forward is not None:
        try:
            from neuromotor.model.kinematics import body_poses

            forward = np.asarray(forward, dtype=np.float64).reshape(3)
            ref_frame = getattr(setup.character.anatomy, "reference_frame", None)
            if ref_frame is not None:
                _, rot_ref = body_poses(model, setup.traj.q(jnp.asarray(float(ref_frame) * clip.frame_time)))
                local = np.asarray(rot_ref)[0].T @ forward
                forward = (quat_to_matrix(jnp.asarray(base.states.quat[:, 0])) @ local).mean(axis=0)
                forward = np.asarray(forward)
        except Exception:  # an anatomy without a usable forward: the skeleton estimate
            forward = None
    arrays["facing"] = facing_direction(arrays["skeleton_points_unperturbed"], arrays["skeleton_edges"],
                                        int(arrays["up_axis"]), forward)
    if getattr(result, "ball", None) is not None:
        arrays.update(contact.ball_arrays(setup, result))
    return arrays


def file_sha256(path) -> str:
    """Hex SHA-256 of a file's bytes."""
    import hashlib

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


def provenance(setup: Setup) -> dict:
    """What made a run, as plain JSON values (RUN.npz ``provenance_json``): the package
    version, the clip file and its SHA-256, and the fully resolved configuration (gains, step,
    window, perturbations with their resolved body and point, units, up axis, stature, mass
    options, ball)."""
    from neuromotor import __version__

    cfg, model, character = setup.config, setup.model, setup.character
    clip = character.source
    clip_path = pathlib.Path(clip.path).resolve()
    anat = getattr(character, "anatomy", None)
    p = setup.pulses
    names = model.body_names
    perts = []
    for i, spec in enumerate(cfg.perturbations):
        b = int(np.asarray(p.body)[i])
        perts.append({
            "kind": spec.get("kind", "force"),
            "body_requested": spec.get("body"),
            "body": names[b],
            "body_index": b,
            "point": _floats(np.asarray(p.point)[i]),
            "point_given": spec.get("point") is not None,
            "direction": _floats(np.asarray(p.direction)[i]),
            "magnitude": float(np.asarray(p.magnitude)[i]),
            "start": float(np.asarray(p.start)[i]),
            "duration": float(np.asarray(p.duration)[i]),
            "shape": p.shape[i],
        })
    ball = None
    if setup.ball is not None:
        b = setup.ball.ball
        ball = {"config": cfg.ball}
        ball.update({f.name: _floats(getattr(b, f.name)) for f in dataclasses.fields(b)})
    elif cfg.ball:
        ball = {"config": cfg.ball}
    sim = setup.sim
    return {
        "neuromotor_version": __version__,
        "jax_version": jax.__version__,
        "config_source": cfg.source,
        "clip": {
            "path": str(clip_path),
            "sha256": file_sha256(clip_path) if clip_path.is_file() else None,
            "frames": int(clip.n_frames),
            "frame_time": float(clip.frame_time),
        },
        "gains": {"ks": float(cfg.ks), "kd": float(cfg.kd), "tau_floor": float(cfg.tau_floor)},
        "h": float(cfg.h),
        "start": float(cfg.start),
        "duration": float(sim.n_steps * cfg.h),
        "n_steps": int(sim.n_steps),
        "implicit": bool(cfg.implicit),
        "stabilization_steps": int(cfg.stabilization_steps),
        "driven_joints": [names[b] for b in sim.driven],
        "perturbations": perts,
        "ball": ball,
        "units": {"requested": cfg.units, "resolved": getattr(anat, "units", None),
                  "length_scale": float(character.clip.length_scale)},
        "up_axis": {"requested": cfg.up_axis, "resolved": up_axis_of(model),
                    "up": _floats(anat.up) if anat is not None else None},
        "stature": {"requested": cfg.stature,
                    "resolved": float(anat.stature) if anat is not None else None},
        "body_mass": {"requested": cfg.body_mass, "total": float(np.sum(np.asarray(model.mass)))},
        "sex": cfg.sex,
        "simulate_extremities": bool(cfg.simulate_extremities),
        "n_bodies": int(model.n_bodies),
        "n_dofs": int(model.n_dofs),
    }


def read_run_info(path) -> dict:
    """Provenance, metrics and array shapes of a RUN.npz; ValueError naming the file when it
    is not one (unreadable, not an .npz, no ``time``/``theta``, malformed JSON)."""
    path = pathlib.Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file")
    if path.is_dir():
        raise ValueError(f"{path}: is a directory, not a run file")
    try:
        with np.load(path, allow_pickle=False) as data:
            shapes = {k: list(data[k].shape) for k in data.files}
            text = {k: str(data[k]) for k in ("provenance_json", "metrics_json") if k in data.files}
    except Exception as e:  # zip, pickle, truncation errors all mean the same to the user
        raise ValueError(f"{path}: not a readable .npz run file ({type(e).__name__}: {e})") from None
    missing = [k for k in ("time", "theta") if k not in shapes]
    if missing:
        raise ValueError(f"{path}: not a neuromotor run file (no {', '.join(missing)} array)")
    out = {"file": str(path), "provenance": None, "metrics": None, "arrays": shapes}
    for key, field in (("provenance_json", "provenance"), ("metrics_json", "metrics")):
        if key in text:
            try:
                out[field] = json.loads(text[key])
            except json.JSONDecodeError as e:
                raise ValueError(f"{path}: {key} is not valid JSON ({e})") from None
    return out


def save_npz_atomic(path, arrays: dict) -> pathlib.Path:
    """Write an .npz through a temporary file in the same folder, then rename."""
    path = pathlib.Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def up_axis_of(model: Model) -> int:
    """The coordinate axis gravity pulls against (0, 1 or 2)."""
    return int(np.argmax(np.abs(np.asarray(model.gravity))))


def clip_of(setup: Setup) -> BvhClip:
    return setup.character.clip
