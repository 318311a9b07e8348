"""The residuals of a capture's inverse dynamics with the ground (issue 38): which feet touch
the floor, the ground reaction forces that best explain the driven root's wrench, and the
residual root force and moment they leave, per step and as RMS and peak, in N, N m and % of
the body weight (moments: % of body weight x stature). The physics is
:mod:`neuromotor.physics.grf`; docs/residuals.md has the figures and the commands.

The floor is the ground's rule (:func:`neuromotor.studies.ground.capture_floor`): the height
along up of the feet's lowest polyhedron vertex over every frame of the clip (every body's
when the rig has no labelled feet; the held frame of a still run). A run with a ground passes
that ground's height, so RUN.npz has one floor.

A flight step is one with no candidate vertex within ``CONTACT_HEIGHT`` of the floor (height
alone: a foot leaving or striking the ground fast is not in flight); there the ground explains
nothing, and the residual is the whole wrench ``m (a_com - g)`` and the rate of the angular
momentum about the COM: zero for a physically consistent capture.
"""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np

from neuromotor.model.kinematics import Trajectory, grid_poses_jit
from neuromotor.model.skeleton import Character
from neuromotor.physics import grf
from neuromotor.physics.contact.detection import up_direction
from neuromotor.physics.contact.ground import world_axes
from neuromotor.physics.dynamics import Reference, StepOptions
from neuromotor.rotations import matrix_to_quat
from neuromotor.studies.ground import capture_floor, friction_axes  # one floor rule, one set of feet, one polygon rule

FOOT = "foot"  # the mass model's segment of the feet (Character.body_segment)
GRAVITY_FALLBACK = 9.81  # m/s^2: the body weight's g on a rig without gravity


def body_height(character: Character, pos, rot, verts, valid) -> float:
    """The stature (m): the anatomy's, else the polyhedra's extent along up at the first pose."""
    stature = getattr(character.anatomy, "stature", None)
    if stature:
        return float(stature)
    height = np.asarray(grf.vertex_world(character.model, verts, pos[0], rot[0]) @ up_direction(character.model))
    return float(np.ptp(height[np.asarray(valid)])) or 1.0


@dataclasses.dataclass(frozen=True)
class Residuals:
    """The contact-aware inverse dynamics of one grid (S steps; N, N m, world)."""

    time: np.ndarray  # (S,) start of each step
    required: np.ndarray  # (S, 6) the driven root's wrench: force, moment about the COM
    com: np.ndarray  # (S, 3) the whole body's COM at the step's start (the moments' point)
    contacts: grf.CaptureContacts  # (S, G) candidates, as NumPy arrays
    ground: grf.GroundReaction  # forces at the candidates, produced wrench, residual
    flight: np.ndarray  # (S,) bool: no candidate within the contact height
    weight: float  # m g (N)
    stature: float  # m
    floor: float  # m along up
    up: np.ndarray  # (3,)

    @property
    def residual(self) -> np.ndarray:
        return self.ground.residual


def capture_residuals(
    character: Character,
    traj: Trajectory,
    ref: Reference,
    options: StepOptions,
    floor: float | None = None,
    mu: float = grf.FRICTION,
    capture: Trajectory | None = None,
) -> Residuals:
    """:class:`Residuals` of the reference's grid (the discrete inverse's velocities; ``options``:
    the step options it was made with; ``floor``: None for :func:`capture_floor`; ``capture``:
    the clip's own trajectory when ``traj`` holds a pose still, for the friction axes)."""
    if ref.velocity is None:
        raise ValueError("contact-aware inverse dynamics needs the discrete feedforward (Reference.velocity)")
    model = character.model
    floor = capture_floor(character, traj) if floor is None else float(floor)
    pos, rot = grid_poses_jit(model, traj, ref.time)
    cfg = dataclasses.replace(options, free_root=False)
    required, com = grf.required_wrench(model, cfg, pos, rot, ref.velocity)
    verts, valid = grf.body_vertices(character.shapes)
    contacts = grf.capture_contacts(model, verts, valid, pos, rot, floor, options.h)
    contacts = jax.tree_util.tree_map(np.asarray, contacts)
    up = np.asarray(up_direction(model))
    g = float(np.linalg.norm(np.asarray(model.gravity))) or GRAVITY_FALLBACK
    weight, stature = float(np.sum(model.mass)) * g, body_height(character, pos, rot, verts, valid)
    local = friction_axes(character, traj if capture is None else capture)  # turned with each body at every step
    steps = np.arange(contacts.body.shape[0])[:, None]
    axes = (
        None if local is None else np.asarray(world_axes(local[contacts.body], np.asarray(rot)[steps, contacts.body]))
    )
    ground = grf.solve_grf(required, contacts, com, up, weight, stature, mu, axes=axes)
    flight = ~np.any(contacts.height < grf.CONTACT_HEIGHT, axis=1)
    return Residuals(
        np.asarray(ref.time[:-1]),
        np.asarray(required),
        np.asarray(com),
        contacts,
        ground,
        flight,
        weight,
        stature,
        floor,
        up,
    )


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else float("nan")


def _peak(x) -> float:
    return float(np.max(x)) if np.size(x) else float("nan")


def _stats(res: Residuals, rows, prefix: str) -> dict:
    """RMS and peak of the residual's force and moment magnitudes over ``rows``."""
    force = np.linalg.norm(res.residual[rows, :3], axis=-1)
    moment = np.linalg.norm(res.residual[rows, 3:], axis=-1)
    bw, bwl = 100.0 / res.weight, 100.0 / (res.weight * res.stature)
    out = {}
    for name, value, scale, unit, pct in (
        ("force", force, bw, "N", "pct_bw"),
        ("moment", moment, bwl, "Nm", "pct_bw_stature"),
    ):
        for stat, fn in (("rms", _rms), ("peak", _peak)):
            v = fn(value)
            out[f"{prefix}{name}_{stat}_{unit}"] = v
            out[f"{prefix}{name}_{stat}_{pct}"] = v * scale
    return out


def flight_phases(flight: np.ndarray) -> list[tuple[int, int]]:
    """``[(first, end)]`` step ranges of consecutive flight steps."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flight.astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def flight_means(res: Residuals) -> np.ndarray:
    """``(phases, 6)``: the residual's mean over each flight phase (its impulse over its
    duration): the part of the capture's inconsistency that is not frame-to-frame noise."""
    phases = flight_phases(res.flight)
    return np.array([res.residual[a:b].mean(0) for a, b in phases]).reshape(-1, 6)


def residual_summary(res: Residuals) -> dict:
    """The figures of ``neuromotor info`` and docs/residuals.md: RMS and peak over the steps of
    the residual force (N, % of body weight) and moment (N m about the COM, % of body weight x
    stature), over all steps and over the flight steps, and the contact settings."""
    steps = res.required.shape[0]
    active = np.asarray(res.contacts.active)
    means = flight_means(res)
    out = {
        "steps": steps,
        "body_weight_N": res.weight,
        "stature_m": res.stature,
        "floor_m": res.floor,
        "contact_height_m": grf.CONTACT_HEIGHT,
        "contact_speed_m_s": grf.CONTACT_SPEED,
        "friction": grf.FRICTION,
        "moment_point": "whole-body COM",
        "contact_fraction": float(np.mean(active.any(1))) if steps else float("nan"),
        # the largest ground reaction force (N): the scale OpenSim's and AddBiomechanics' residual
        # criteria use ("% of the peak external force"); docs/residuals.md
        "grf_peak_N": _peak(np.linalg.norm(res.ground.produced[:, :3], axis=-1)),
        **_stats(res, slice(None), ""),
        "flight_fraction": float(np.mean(res.flight)) if steps else float("nan"),
        "flight_phases": len(means),
        **_stats(res, res.flight, "flight_"),
        "flight_mean_force_max_pct_bw": _peak(np.linalg.norm(means[:, :3], axis=-1) * 100.0 / res.weight),
    }
    return {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in out.items()}


def contact_bodies(res: Residuals) -> np.ndarray:
    """The bodies with a touching candidate at some step, in body order."""
    active = np.asarray(res.contacts.active)
    return np.unique(np.asarray(res.contacts.body)[active]).astype(np.int64)


def body_loads(res: Residuals, bodies) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step and contact body: the ground reaction force ``(S, K, 3)``, its centre of pressure
    on the floor plane ``(S, K, 3)`` and the free torque about it ``(S, K, 3)``, along up (OpenSim's
    ExternalForce: force, point, torque). Without normal force the point is the mean of the
    body's candidates on the plane."""
    body, point, force = np.asarray(res.contacts.body), np.asarray(res.contacts.point), res.ground.force
    up, steps = res.up, force.shape[0]
    base = res.floor * up
    f_out, p_out, t_out = (np.zeros((steps, len(bodies), 3)) for _ in range(3))
    for j, b in enumerate(bodies):
        mine = (body == b)[..., None]
        f = np.where(mine, force, 0.0)
        total = f.sum(1)
        moment = np.cross(point - base, f).sum(1)  # about the floor point below the origin
        normal = total @ up
        mean = np.where(mine, point, 0.0).sum(1) / np.maximum(mine.sum(1), 1)
        fallback = mean - np.outer(mean @ up - res.floor, up)
        x = np.cross(up, moment) / np.where(normal > 1e-9 * res.weight, normal, np.inf)[:, None]
        cop = np.where((normal > 1e-9 * res.weight)[:, None], base + x, fallback)
        f_out[:, j], p_out[:, j] = total, cop
        t_out[:, j] = moment - np.cross(cop - base, total)
    return f_out, p_out, t_out


def _grid(a: np.ndarray) -> np.ndarray:
    """Per-step values on the run's T = S + 1 samples (the last step's repeated, as the
    reference's feedforward)."""
    return np.concatenate([a, a[-1:]], 0)


def residual_arrays(res: Residuals) -> dict[str, np.ndarray]:
    """The residuals' part of RUN.npz (:mod:`neuromotor.io.runfile`, ``RESIDUAL_FIELDS``)."""
    bodies = contact_bodies(res)
    force, point, torque = body_loads(res, bodies)
    return {
        "residual_force": _grid(res.residual[:, :3]),
        "residual_moment": _grid(res.residual[:, 3:]),
        "residual_point": _grid(res.com),
        "grf_force": _grid(force),
        "grf_point": _grid(point),
        "grf_torque": _grid(torque),
        "grf_body": bodies,
        "contact_points": _grid(np.asarray(res.contacts.active).sum(1).astype(np.int64)),
        "residuals_json": np.asarray(json.dumps(residual_summary(res))),
    }


def ground_reference(
    character: Character, traj: Trajectory, ref: Reference, options: StepOptions, res: Residuals | None = None
) -> tuple[Reference, Residuals]:
    """The reference of a body held up by the ground (a free root): the same targets, with the
    feedforward of the discrete inverse that applies the capture's ground reaction forces as
    known external forces (:func:`neuromotor.physics.grf.contact_feedforward`), so that only the
    residual is left unexplained; and the :class:`Residuals` it used. ``ref``: the reference the
    driven root's discrete inverse made (``make_reference`` with ``free_root`` off); ``res``:
    :func:`capture_residuals` of it, if already computed."""
    res = capture_residuals(character, traj, ref, options) if res is None else res
    model = character.model
    pos, rot = grid_poses_jit(model, traj, ref.time)
    external = grf.body_wrenches(model, res.contacts, res.ground.force, np.asarray(pos))
    cfg = dataclasses.replace(options, free_root=False)
    tau, _, _ = grf.contact_feedforward(model, cfg, ref, matrix_to_quat(rot), jnp.asarray(external))
    return grf.with_feedforward(model, ref, tau), res
