"""External perturbations: force pulses and impulses at points on named bodies, and the base motion.

A pulse on body b at body-frame point p (metres, relative to the body's joint origin) applies
the world force ``F(t) = magnitude * direction * shape((t - start) / duration)`` at the moving
point, i.e. force F on the body and torque ``(x_p - c_b) x F`` about its COM. Shapes (unit peak):
``square`` (1 on [0, 1)), ``half_sine`` (sin(pi s) on [0, 1]), ``triangle``. An impulse of
``magnitude`` N s is a square pulse of one time step and magnitude / h newtons, applied in the
step that starts at the grid time nearest ``start``.

A base motion (kind ``base``: a sled, a vehicle, a platform) adds a prescribed acceleration a(t)
to the driven root's path, and through the root and the driven joints to every driven body: a
pulse of ``magnitude`` (m/s^2) along ``direction`` with a shape, or a recorded series (piecewise
linear between its samples, zero outside them). The feedforward stays the capture's (the person
does not anticipate the jolt). On the grid t_k it is the root's added velocity V_k = int a dt
(exact for both forms) and displacement D_k, with D_0 = 0 and D_k+1 = D_k + h V_k+1: the step's
own position update, so a base-motion run equals the unperturbed frame's run under the inertial
forces -m_b (V_k+1 - V_k) / h on every body to round-off (tests/physics/test_base_motion.py).
Under a free root on a ground the same V_k and D_k move the ground instead (a platform:
:class:`neuromotor.physics.contact.step.GroundMotion`).

A tilt (kind ``tilt``, a free root only) turns that ground about an axis through ``pivot`` (world,
m; default the ground point under the whole-body COM of the run's first pose): ``magnitude``
degrees about ``direction`` (right-hand rule: about ``right``, toes up), reached over
``duration`` with the angular velocity's ``shape``, then held. Several tilts add their rotation
vectors. On the grid the platform's orientation R_k is exact (``base_turn``, unit quaternions) and
its angular velocity over step k is the secant ``Omega_k+1 = log(R_k+1 R_k^T) / h``
(``base_spin``), so R_k+1 = exp(h Omega_k+1) R_k: the step's own update, as for D_k.

Every field is an array leaf with a leading axis P (several pulses per run; the shape too, as an
index into :data:`SHAPES`), so a batch of magnitudes, directions, bodies, start times or shapes is
a ``vmap`` over this container, and runs that differ only in their pulses share one program. The
base motion is two (S+1, 3) leaves on the grid (None without one: the step is today's).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor import rotations_np as rnp
from neuromotor.rotations import mv

SHAPES = ("square", "half_sine", "triangle")
# Each kind: the fields it reads (the config refuses the others), and its magnitude's unit (a base
# motion's is its ``unit`` field: g or m/s^2). A force pulse has a shape and duration; an impulse
# acts within one step; a base motion moves no body point but the driven root's path, as a pulse
# or as a recorded series (``file``, whose samples replace magnitude, shape and duration).
KIND_FIELDS = {
    "force": ("body", "point", "direction", "magnitude", "start", "duration", "shape"),
    "impulse": ("body", "point", "direction", "magnitude", "start"),
    "base": ("direction", "magnitude", "start", "duration", "shape", "file", "unit", "time_unit"),
    "tilt": ("direction", "magnitude", "start", "duration", "shape", "pivot"),
}
UNITS = {"force": "N", "impulse": "N s", "base": "m/s^2", "tilt": "deg"}
PLATFORM_KINDS = ("base", "tilt")  # kinds that move what the character stands on, not a body
KINDS = tuple(KIND_FIELDS)
STANDARD_GRAVITY = 9.80665  # m/s^2 per g (the unit of accelerations, not the model's gravity)
ACCELERATION_UNITS = {"g": STANDARD_GRAVITY, "m/s^2": 1.0}  # SI per unit
TIME_UNITS = {"s": 1.0, "ms": 1e-3}


def acting_interval(kind: str, start: float, duration: float, h: float) -> tuple[float, float]:
    """Clip seconds [t0, t1) a perturbation of ``kind`` pushes: an impulse the one step centred
    on ``start`` (exactly one sample of the time grid falls inside, whatever the round-off of
    t_k = t_0 + k h), a force pulse or base pulse its ``duration`` from ``start`` (a recorded
    base series: ``start`` is its first sample, ``duration`` its span)."""
    if kind == "impulse":
        return start - 0.5 * h, start + 0.5 * h
    return start, start + duration


class ForcePulses(eqx.Module):
    body: Int[Array, " P"]
    point: Float[Array, "P 3"]  # body frame, relative to the joint origin (m)
    direction: Float[Array, "P 3"]  # world, unit
    magnitude: Float[Array, " P"]  # N (peak)
    start: Float[Array, " P"]  # s
    duration: Float[Array, " P"]  # s
    shape: Int[Array, " P"]  # index into SHAPES
    # The base motion on the grid t_0..t_S (world, m/s and m): the driven root's added velocity
    # V_k and displacement D_k; None: no base motion.
    base_velocity: Float[Array, "S1 3"] | None = None
    base_offset: Float[Array, "S1 3"] | None = None
    # A tilt of the ground (free root): its orientation R_k (unit quaternions), its angular
    # velocity Omega_k over the step ending at t_k (world, rad/s; Omega_0 = 0) and the point it
    # turns about (world, m); None: no tilt. A tilt comes with a (possibly zero) base motion.
    base_turn: Float[Array, "S1 4"] | None = None
    base_spin: Float[Array, "S1 3"] | None = None
    base_pivot: Float[Array, " 3"] | None = None

    @property
    def count(self) -> int:
        return self.magnitude.shape[-1]

    def pivot_at(self, k):
        """Where the tilt's pivot is at grid step k (world, m; carried by the base motion's
        displacement); None without a tilt."""
        if self.base_spin is None:
            return None
        assert self.base_pivot is not None and self.base_offset is not None
        return self.base_pivot + self.base_offset[k]


def no_pulses() -> ForcePulses:
    z = jnp.zeros((0,))
    return ForcePulses(
        jnp.zeros((0,), jnp.int32), jnp.zeros((0, 3)), jnp.zeros((0, 3)), z, z, z, jnp.zeros((0,), jnp.int32)
    )


def vector_direction(value, time: float) -> np.ndarray:
    """A direction given as 3 numbers, made unit (keywords need the character: see
    :func:`neuromotor.studies.simulate.direction_lookup`)."""
    if isinstance(value, str):
        raise ValueError(f"direction {value!r} is a keyword of the character's frame: build with its direction_of")
    direction = np.asarray(value, np.float64)
    norm = np.linalg.norm(direction)
    if not norm > 0:
        raise ValueError(f"perturbation direction must be non-zero, got {value}")
    return direction / norm


def build_pulses(
    specs, model, h: float, body_index, direction_of=vector_direction, times=None, pivot=None
) -> ForcePulses:
    """The one way from the user's perturbations to the arrays the step consumes.

    ``specs``: mappings with every field of :class:`neuromotor.config.specs.PerturbationSpec`
    (kind, body, point, direction, magnitude, start, duration, shape; the defaults live there,
    not here). ``point`` None is the body's COM (``model.com``); an impulse (N s) becomes a
    square pulse of one step ``h`` and magnitude / h newtons. ``body_index`` maps a name to an
    index; ``direction_of(value, start)`` a direction (3 numbers or a keyword of the character's
    frame, taken at the perturbation's start) to a world unit vector. Base motions need the grid
    ``times`` (t_0..t_S, s; :func:`base_motion`); a tilt without its own ``pivot`` turns about
    ``pivot`` (world, m: the setup's default).
    """
    bases = [s for s in specs if s["kind"] == "base"]
    tilts = [s for s in specs if s["kind"] == "tilt"]
    pulses = _force_pulses([s for s in specs if s["kind"] not in PLATFORM_KINDS], model, h, body_index, direction_of)
    if not bases and not tilts:
        return pulses
    if times is None:
        raise ValueError("a base motion or a tilt needs the simulation grid (times)")
    times = np.asarray(times, np.float64)
    velocity, offset = base_motion(bases, times, h, direction_of)
    pulses = dataclasses.replace(pulses, base_velocity=jnp.asarray(velocity), base_offset=jnp.asarray(offset))
    if not tilts:
        return pulses
    turn, spin, centre = tilt_motion(tilts, times, h, direction_of, pivot)
    return dataclasses.replace(
        pulses, base_turn=jnp.asarray(turn), base_spin=jnp.asarray(spin), base_pivot=jnp.asarray(centre)
    )


def _force_pulses(specs, model, h: float, body_index, direction_of) -> ForcePulses:
    if not specs:
        return no_pulses()
    rows = [_pulse(s, model, h, body_index, direction_of) for s in specs]
    body, point, direction, magnitude, start, duration, shape = zip(*rows)
    return ForcePulses(
        jnp.asarray(body, jnp.int32),
        jnp.asarray(np.stack(point)),
        jnp.asarray(np.stack(direction)),
        jnp.asarray(magnitude),
        jnp.asarray(start),
        jnp.asarray(duration),
        jnp.asarray([SHAPES.index(x) for x in shape], jnp.int32),
    )


def _pulse(s, model, h: float, body_index, direction_of) -> tuple:
    """One pulse's fields from one spec (see :func:`build_pulses`)."""
    if s["kind"] not in KINDS:
        raise ValueError(f"perturbation kind must be one of {KINDS}, got {s['kind']!r}")
    direction = direction_of(s["direction"], float(s["start"]))  # host arrays: a sweep builds one per run
    b = body_index(s["body"])
    point = np.asarray(model.com[b] if s["point"] is None else s["point"], np.float64)
    magnitude, start = float(s["magnitude"]), float(s["start"])
    duration, shape = float(s.get("duration", h)), s.get("shape", "square")  # an impulse has neither
    if s["kind"] == "impulse":  # N s as a square pulse of magnitude / h over its acting step
        start = acting_interval("impulse", start, duration, h)[0]
        magnitude, duration, shape = magnitude / h, h, "square"
    if shape not in SHAPES:
        raise ValueError(f"perturbation shape must be one of {SHAPES}, got {shape!r}")
    return (b, point, direction, magnitude, start, float(duration), shape)


def profile_integral(shape: str, s) -> np.ndarray:
    """int_0^s of the unit-peak profile of ``shape`` (phase units; s clipped to [0, 1])."""
    c = np.clip(np.asarray(s, np.float64), 0.0, 1.0)
    if shape == "square":
        return c
    if shape == "half_sine":
        return (1.0 - np.cos(np.pi * c)) / np.pi
    if shape == "triangle":
        return np.where(c <= 0.5, c * c, 2.0 * c - c * c - 0.5)
    raise ValueError(f"perturbation shape must be one of {SHAPES}, got {shape!r}")


def series_integral(t_rec, a_rec, t) -> np.ndarray:
    """int_-inf^t a of the piecewise linear series (t_rec, a_rec), zero outside its samples."""
    t_rec, a_rec, t = (np.asarray(x, np.float64) for x in (t_rec, a_rec, t))
    dt = np.diff(t_rec)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * dt * (a_rec[1:] + a_rec[:-1]))])
    i = np.clip(np.searchsorted(t_rec, t, side="right") - 1, 0, len(t_rec) - 2)
    u = np.clip(t, t_rec[i], t_rec[i + 1]) - t_rec[i]
    inside = cum[i] + a_rec[i] * u + 0.5 * (a_rec[i + 1] - a_rec[i]) / dt[i] * u * u
    return np.where(t < t_rec[0], 0.0, np.where(t >= t_rec[-1], cum[-1], inside))


def base_motion(specs, times: np.ndarray, h: float, direction_of=vector_direction) -> tuple[np.ndarray, np.ndarray]:
    """The driven root's added velocity V_k and displacement D_k on the grid ``times`` (S+1,) of
    the base motions ``specs`` (module docstring): V_k exact, D_0 = 0, D_k+1 = D_k + h V_k+1."""
    velocity = np.zeros((times.shape[0], 3))
    for s in specs:
        scale = ACCELERATION_UNITS[s["unit"]]
        direction = direction_of(s["direction"], float(s["start"]))
        if s.get("file") is not None:
            t_rec, a_rec = s["record"]
            dv = series_integral(float(s["start"]) + np.asarray(t_rec), np.asarray(a_rec) * scale, times)
        else:
            duration = float(s["duration"])
            phase = (times - float(s["start"])) / duration
            dv = float(s["magnitude"]) * scale * duration * profile_integral(s["shape"], phase)
        velocity += dv[:, None] * direction
    offset = np.concatenate([np.zeros((1, 3)), h * np.cumsum(velocity[1:], axis=0)], 0)
    return velocity, offset


def tilt_motion(specs, times: np.ndarray, h: float, direction_of=vector_direction, pivot=None):
    """The tilts ``specs`` on the grid ``times`` (S+1,) (module docstring): the platform's
    orientation R_k as unit quaternions (S+1, 4), its secant angular velocity Omega_k (S+1, 3;
    Omega_0 = 0) and the pivot (3,). All tilts of a run share one pivot (one platform)."""
    rotvec = np.zeros((times.shape[0], 3))
    centres: list[np.ndarray | None] = []
    for s in specs:
        axis = direction_of(s["direction"], float(s["start"]))
        duration = float(s["duration"])
        fraction = profile_integral(s["shape"], (times - float(s["start"])) / duration)
        fraction = fraction / profile_integral(s["shape"], 1.0)  # 0 before, 1 from start + duration on
        rotvec += np.deg2rad(float(s["magnitude"])) * fraction[:, None] * axis
        c = s.get("pivot") if s.get("pivot") is not None else pivot
        centres.append(None if c is None else np.asarray(c, np.float64))
    given = [c for c in centres if c is not None]
    if len(given) < len(centres):
        raise ValueError("a tilt needs a pivot (give pivot, or build it with the setup's default)")
    if any(np.abs(c - given[0]).max() > 1e-12 for c in given):
        raise ValueError("the tilts of a run turn one platform: give them one pivot")
    turn = rnp.quat_exp(rotvec)
    spin = np.zeros_like(rotvec)
    spin[1:] = rnp.quat_log(rnp.quat_mul(turn[1:], rnp.quat_conj(turn[:-1]))) / h
    return turn, spin, given[0]


def stack_runs(runs) -> ForcePulses:
    """Runs' perturbations stacked along a new leading axis: runs with fewer pulses are padded
    with zero-magnitude ones (no force), runs without a base motion get a zero one when another
    has one, so cases of any kinds share one program."""
    n = max(r.count for r in runs)
    grid = next((r.base_velocity.shape for r in runs if r.base_velocity is not None), None)
    tilted = next((r for r in runs if r.base_turn is not None), None)
    padded = []
    for r in runs:
        extra = n - r.count
        if extra:
            pad = ForcePulses(
                jnp.zeros((extra,), jnp.int32),
                jnp.zeros((extra, 3)),
                jnp.tile(jnp.asarray([[1.0, 0.0, 0.0]]), (extra, 1)),
                jnp.zeros((extra,)),
                jnp.zeros((extra,)),
                jnp.ones((extra,)),
                jnp.zeros((extra,), jnp.int32),
            )
            r = dataclasses.replace(r, **{f: jnp.concatenate([getattr(r, f), getattr(pad, f)]) for f in POINT_FIELDS})
        if grid is not None and r.base_velocity is None:
            r = dataclasses.replace(r, base_velocity=jnp.zeros(grid), base_offset=jnp.zeros(grid))
        if tilted is not None and r.base_turn is None:  # level and still, about the same pivot
            still = jnp.zeros((grid[0], 4)).at[:, 0].set(1.0)  # type: ignore[index]
            r = dataclasses.replace(r, base_turn=still, base_spin=jnp.zeros(grid), base_pivot=tilted.base_pivot)
        padded.append(r)
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *padded)


POINT_FIELDS = ("body", "point", "direction", "magnitude", "start", "duration", "shape")  # the P-axis leaves


def unperturbed(p: ForcePulses) -> ForcePulses:
    """The unperturbed twin: the same pulses at zero magnitude, a zero base motion and a level,
    still platform (same shapes, one program)."""
    if p.base_velocity is None or p.base_offset is None:
        return dataclasses.replace(p, magnitude=p.magnitude * 0)
    p = dataclasses.replace(
        p, magnitude=p.magnitude * 0, base_velocity=p.base_velocity * 0, base_offset=p.base_offset * 0
    )
    if p.base_turn is None or p.base_spin is None:
        return p
    return dataclasses.replace(p, base_turn=jnp.zeros_like(p.base_turn).at[..., 0].set(1.0), base_spin=p.base_spin * 0)


def pulse_profile(shape, s):
    """Unit-peak profile at phase ``s`` of shape ``shape`` (an index into SHAPES, or its name)."""
    shape = SHAPES.index(shape) if isinstance(shape, str) else shape
    inside = (s >= 0.0) & (s < 1.0)
    c = jnp.clip(s, 0.0, 1.0)
    val = jnp.select([shape == 0, shape == 1], [jnp.ones_like(s), jnp.sin(jnp.pi * c)], 1.0 - jnp.abs(2.0 * c - 1.0))
    return jnp.where(inside, val, 0.0)


def pulse_forces(p: ForcePulses, t) -> Float[Array, "P 3"]:
    """World force vector of each pulse at time t."""
    if p.count == 0:
        return jnp.zeros((0, 3))
    prof = pulse_profile(p.shape, (t - p.start) / p.duration)
    return (p.magnitude * prof)[:, None] * p.direction


def pulse_wrenches(
    p: ForcePulses, t, n_bodies: int, pos, rot, com
) -> tuple[Float[Array, " 6B"], Float[Array, "B 3"], Float[Array, "P 3"]]:
    """The pulses' wrenches at time t: as a generalized force (6B: each body's force and torque
    about its COM), the force on each body (B, 3), and the pulses' world points (P, 3)."""
    zeros = jnp.zeros((n_bodies, 6), pos.dtype)
    if p.count == 0:
        return zeros.reshape(-1), jnp.zeros((n_bodies, 3), pos.dtype), jnp.zeros((0, 3), pos.dtype)
    force = pulse_forces(p, t)
    lever = mv(rot[p.body], p.point - com[p.body])
    torque = jnp.cross(lever, force)
    gen = zeros.at[p.body, :3].add(force).at[p.body, 3:].add(torque)
    per_body = jnp.zeros((n_bodies, 3), pos.dtype).at[p.body].add(force)
    return gen.reshape(-1), per_body, pos[p.body] + lever
