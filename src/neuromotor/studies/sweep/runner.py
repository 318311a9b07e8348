"""Sharded execution of a sweep: chunks of runs over a 1-D device mesh, baselines first, exact
recovery metrics on the host per chunk."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from neuromotor import compiler
from neuromotor.distributed import gather_shares, share
from neuromotor.model.skeleton import Model
from neuromotor.physics import solvers
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import Params, Reference, SimModel, StepOptions, simulate
from neuromotor.physics.perturbation import ForcePulses, unperturbed, vector_direction
from neuromotor.studies import metrics as mx
from neuromotor.studies.sweep.grid import METRIC_KEYS, RunBatch, RunOut, build_batch, gain_keys, reflex_columns

AXIS = "runs"


def device_mesh(devices=None) -> Mesh:
    """A 1-D mesh over ``devices`` (default: this process's devices; with several processes each
    runs its own share of a sweep, see :mod:`neuromotor.distributed`)."""
    devices = jax.local_devices() if devices is None else list(devices)
    return Mesh(np.array(devices), (AXIS,))


def _lapack_on_cpu(options: StepOptions, devices) -> bool:
    """Batched LAPACK calls on several XLA:CPU devices at once can deadlock: such steps
    (:func:`~neuromotor.physics.solvers.uses_lapack`) keep to one CPU device (GPUs are not affected)."""
    return devices[0].platform == "cpu" and solvers.uses_lapack(options.solver, options.driven, options.free_root)


def batch_mesh(size: int, options: StepOptions, devices=None) -> Mesh | None:
    """The mesh :func:`shard_vmap` splits a batch of ``size`` rollouts with ``options`` over: this
    process's devices when there are several, ``size`` divides among them, and the step is not a
    LAPACK step on CPU devices (:func:`_lapack_on_cpu`). None: one ``vmap`` on one device."""
    devices = jax.local_devices() if devices is None else list(devices)
    if len(devices) < 2 or size % len(devices) or _lapack_on_cpu(options, devices):
        return None
    return device_mesh(devices)


def shard_vmap(fn, mesh: Mesh | None):
    """``g(batch, shared) = jax.vmap(lambda x: fn(x, shared))(batch)``, with the batch's leading
    axis split over ``mesh`` (one ``vmap`` per device, by ``shard_map``; ``shared`` replicated).
    ``mesh`` None: the plain ``vmap``. Each device then runs its share on its own core."""
    many = lambda batch, shared: jax.vmap(lambda x: fn(x, shared))(batch)
    if mesh is None:
        return many
    return jax.shard_map(many, mesh=mesh, in_specs=(P(AXIS), P()), out_specs=P(AXIS), check_vma=False)


def _put(x, mesh: Mesh, spec: P):
    """A device array from host data, laid out by ``spec`` over ``mesh``."""
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, NamedSharding(mesh, spec), lambda idx: x[idx])


class Sweeper:
    """Compiled chunk runner for one model, reference and step configuration.

    ``run_chunk(batch)`` simulates ``chunk`` runs (a :class:`RunBatch` padded to ``chunk``)
    sharded over ``mesh``; build it once and reuse it: every call with the same chunk size
    reuses the compiled program.
    """

    def __init__(
        self,
        model: Model,
        ref: Reference,
        options: StepOptions,
        *,
        chunk: int = 64,
        inner_batch: int = 1,
        mesh: Mesh | None = None,
        metric: str = "geodesic",
    ):
        if metric not in mx.DEVIATION_METRICS:
            raise ValueError(f"metric must be one of {mx.DEVIATION_METRICS}, got {metric!r}")
        self.metric = metric
        if mesh is None:
            local = jax.local_devices()
            mesh = device_mesh(local[:1] if _lapack_on_cpu(options, local) else local)
        self.mesh = mesh
        n_dev = self.mesh.devices.size
        self.chunk = max(n_dev, int(math.ceil(chunk / n_dev)) * n_dev)
        self.inner_batch = max(1, min(int(inner_batch), self.chunk // n_dev))
        if self.inner_batch > 1:  # rollouts vmapped together: the solver that vectorizes in a batch
            options = dataclasses.replace(options, solver=options.solver.batched())
        self.options, self.n_steps = options, options.n_steps
        self.model = model  # host copy: the one pulse builder reads each body's COM
        self.times = np.asarray(ref.time)  # host copy: the grid a base motion is built on
        arrays, static = eqx.partition(model, eqx.is_array)
        self.shared = jax.tree_util.tree_map(lambda x: _put(x, self.mesh, P()), (arrays, ref))
        self._simulate = self._program(static)

    def _program(self, static):
        """The compiled chunk, ``f(shared, batch) -> RunOut`` (shared by sweepers of one layout)."""
        return _chunk_program(_Layout(static), self.options, self.metric, self.inner_batch, self.mesh)

    def pose(self, model: Model, r):
        """What d(t) is measured on (:class:`RunOut`): local joint quaternions, or theta (euler)."""
        return _pose(self.metric, model, r)

    def pad(self, batch: RunBatch, lo: int, hi: int) -> RunBatch:
        """Rows lo:hi of a host batch, padded to the chunk size by repeating the last row."""
        idx = np.minimum(np.arange(lo, lo + self.chunk), hi - 1)
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[idx], batch)

    def simulate_chunk(self, batch: RunBatch) -> RunOut:
        """Device-resident outputs of one padded chunk (sharded along the run axis)."""
        placed = jax.tree_util.tree_map(lambda x: _put(x, self.mesh, P(AXIS)), batch)
        return self._simulate(self.shared, placed)


def _pose(metric: str, model: Model, r):
    return r.theta if metric == "euler" else mx.joint_quats(model, r.states.quat)


class _Layout:
    """The static part of a model as a cache key: sweeps of one skeleton share their program
    (the model's arrays are arguments), so a process that sweeps again does not compile again."""

    def __init__(self, static):
        self.static = static
        leaves, tree = jax.tree_util.tree_flatten(static)
        self._key = (tree, tuple(leaves))

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _Layout) and self._key == other._key


@functools.lru_cache(maxsize=16)
def _chunk_program(layout: _Layout, options: StepOptions, metric: str, inner_batch: int, mesh: Mesh):
    """``f(shared, batch) -> RunOut``: a chunk of rollouts sharded over ``mesh``, ``jax.lax.map``
    over each shard's runs (``inner_batch`` of them vmapped together)."""

    def one(shared, run: RunBatch) -> RunOut:
        model = eqx.combine(shared[0], layout.static)
        r = simulate(SimModel(model, shared[1], options), Params(run.gains, run.pulses))
        return RunOut(
            _pose(metric, model, r), r.diverged_step, r.diverged_body, jnp.max(r.residual), jnp.max(r.violation)
        )

    def local(shared, batch: RunBatch) -> RunOut:
        return jax.lax.map(functools.partial(one, shared), batch, batch_size=None if inner_batch == 1 else inner_batch)

    return compiler.jit(jax.shard_map(local, mesh=mesh, in_specs=(P(), P(AXIS)), out_specs=P(AXIS), check_vma=False))


@compiler.jit
def _chunk_deviation(pose, base_pose, slot):
    """d(t) of each run of a chunk against its twin: geodesic on local joint quaternions
    (S1, C, 4) per run, the Euler-DOF form on angles (S1, n)."""
    dev = mx.rms_joint_angle_deg if pose.ndim == 4 else mx.deviation
    return jax.vmap(dev)(pose, base_pose[slot])


@dataclasses.dataclass
class SweepResult:
    rows: list[dict]  # one per run: inputs, metrics, diagnostics (COLUMNS)
    curves: np.ndarray | None  # (N, S+1) deviation curves, if kept
    time: np.ndarray  # (S+1,) clip time of the samples


def _simulate_baselines(sweeper, base_batch, n_base: int, bar):
    """Unperturbed twin runs (one per gain setting), in chunks: their pose, diverged step and,
    where the runs record it (on the ground), their whole-body COM (else None)."""
    theta, bad, com = [], [], []
    for lo in range(0, n_base, sweeper.chunk):
        hi = min(lo + sweeper.chunk, n_base)
        out = sweeper.simulate_chunk(sweeper.pad(base_batch, lo, hi))
        theta.append(np.asarray(out.pose)[: hi - lo])
        bad.append(np.asarray(out.diverged_step)[: hi - lo])
        if hasattr(out, "com"):
            com.append(np.asarray(out.com)[: hi - lo])
        bar.update(hi - lo)
    return jnp.asarray(np.concatenate(theta)), np.concatenate(bad), np.concatenate(com) if com else None


def run_sweep(
    sweeper: Sweeper,
    gains: Gains,
    pulses: ForcePulses,
    runs: list[dict],
    body_index,
    body_names: Sequence[str],
    *,
    keep_curves: bool = False,
    progress: bool = True,
    direction_of=vector_direction,
    extra=None,
    pivot=None,
) -> SweepResult:
    """Simulate every run of ``runs`` (from :meth:`SweepSpec.runs`) and measure its recovery;
    ``direction_of`` resolves a direction keyword (:func:`~neuromotor.studies.simulate.direction_lookup`);
    ``extra(batch, i, outputs)``: more of run i's row (a sweep on the ground: its metrics);
    ``pivot``: where a tilt without its own turns the ground (the setup's ``tilt_pivot``)."""
    from tqdm.auto import tqdm

    times = sweeper.times
    batch = build_batch(gains, pulses, runs, body_index, sweeper.options.h, sweeper.model, direction_of, times, pivot)
    directions = [run_direction(r, direction_of) for r in runs]  # the world vectors the runs used
    first, slot = gain_keys(batch)
    # Baselines: the distinct gain settings without any pulse, simulated with the same program.
    base = jax.tree_util.tree_map(lambda x: np.asarray(x)[first], batch)
    base = dataclasses.replace(base, pulses=unperturbed(base.pulses))

    def row(i: int, out: dict, dev, time) -> dict:
        r, g = runs[i], runs[i]["gain"]
        d = directions[i]
        return {
            "run": i,
            "kind": r["kind"],
            "label": g.name,
            "controller": g.controller,
            "ks": g.ks,
            "kd": g.kd,
            **reflex_columns(r, gains.reflex),
            "body": r["body"] or "",  # a base motion pushes no body
            "magnitude": r["magnitude"],
            "direction_x": float(d[0]),
            "direction_y": float(d[1]),
            "direction_z": float(d[2]),
            "start": r["start"],
            "duration": r["duration"],
            **mx.recovery_metrics(time, dev, r["onset"]),
            **({} if extra is None else extra(batch, i, out)),
            "max_kkt_residual": float(out["max_residual"]),
            "max_constraint_violation": float(out["max_violation"]),
        }

    bar = tqdm(total=len(first) + len(runs), desc="sweep", unit="run", disable=not progress)
    return sweep_batches(
        sweeper, batch, base, slot, row, lambda out: body_names[int(out["diverged_body"])], bar, keep_curves
    )


def run_direction(run: dict, direction_of) -> np.ndarray:
    """The world unit direction of a run's varied perturbation (a keyword resolved at its start)."""
    p = run["perturbation"]
    return np.asarray(direction_of(p["direction"], float(p["start"])))


def flag_divergence(row: dict, step: int, base_step: int, time, body) -> dict:
    """Keep a run that blew up (or whose twin did), flagged, with the metrics that a frozen
    blown-up state would fake blanked; ``body()`` names the body it blew up in."""
    if step >= 0 or base_step >= 0:
        s = step if step >= 0 else base_step
        row.update({k: float("nan") for k in METRIC_KEYS})
        row.update(
            diverged=True,
            diverged_step=s,
            diverged_time_s=float(time[min(s + 1, len(time) - 1)]),
            diverged_body=body() if step >= 0 else "baseline",
        )
    else:
        row.update(diverged=False, diverged_step=-1, diverged_time_s=float("nan"), diverged_body="")
    return row


def _simulate_share(sweeper: Sweeper, batch, base_batch, slot, lo: int, hi: int, bar) -> dict[str, np.ndarray]:
    """Runs lo:hi of ``batch`` and the twins they need: per run, the deviation curve ``dev``,
    the outputs but the pose, ``base_step`` (the twin's diverged step) and, on the ground,
    ``base_com`` (the twin's COM)."""
    c = sweeper.chunk
    need, local_slot = np.unique(slot[lo:hi], return_inverse=True)
    base = jax.tree_util.tree_map(lambda x: np.asarray(x)[need], base_batch)
    bar.reset(total=len(need) + hi - lo)
    base_theta, base_step, base_com = _simulate_baselines(sweeper, base, len(need), bar)
    parts = []
    for a in range(lo, hi, c):
        b = min(a + c, hi)
        out = sweeper.simulate_chunk(sweeper.pad(batch, a, b))
        slot_c = local_slot.reshape(-1)[np.minimum(np.arange(a, a + c), b - 1) - lo]
        part = {f.name: np.asarray(getattr(out, f.name))[: b - a] for f in dataclasses.fields(out) if f.name != "pose"}
        part["dev"] = np.asarray(_chunk_deviation(out.pose, base_theta, jnp.asarray(slot_c)))[: b - a]
        part["base_step"] = base_step[slot_c[: b - a]]
        if base_com is not None:
            part["base_com"] = base_com[slot_c[: b - a]]
        parts.append(part)
        bar.update(b - a)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def sweep_batches(
    sweeper: Sweeper, batch, base_batch, slot, make_row, body_name, bar, keep_curves: bool = False
) -> SweepResult:
    """Every run of ``batch`` in chunks, after the twins they need:
    ``make_row(i, outputs, d(t), time)`` gives run i's row, ``body_name(outputs)`` the body a
    diverged run blew up in. With several processes (``jax.distributed``) each simulates its
    share of the runs and every process gets all rows in grid order (:mod:`neuromotor.distributed`)."""
    n = len(slot)
    time = np.asarray(sweeper.shared[1].time)[: sweeper.n_steps + 1]
    lo, hi = share(n)
    # An empty share (more processes than runs) simulates one run for the shapes; the gather drops it.
    local = _simulate_share(sweeper, batch, base_batch, slot, min(lo, n - 1), max(hi, min(lo + 1, n)), bar)
    full = gather_shares(local, n)
    rows = []
    for i in range(n):
        h = {k: v[i] for k, v in full.items() if k not in ("dev", "base_step")}
        row = make_row(i, h, full["dev"][i], time)
        rows.append(
            flag_divergence(row, int(h["diverged_step"]), int(full["base_step"][i]), time, lambda: body_name(h))
        )
    bar.close()
    return SweepResult(rows, full["dev"] if keep_curves else None, time)
