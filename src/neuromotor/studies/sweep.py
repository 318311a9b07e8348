"""Batch sweeps: many perturbed rollouts as one jitted computation, sharded over all devices.

A sweep is a flat list of runs. Each run is a :class:`~neuromotor.physics.control.Gains` and a
:class:`~neuromotor.physics.perturbation.ForcePulses` (same static layout for all runs; the first pulse
is the one a grid varies). Runs go through the device(s) in chunks:

* the batch axis of a chunk is sharded over ``jax.devices()`` with a 1-D
  :class:`jax.sharding.Mesh` and :func:`jax.shard_map`; the same code spreads over several
  GPUs, or several hosts after ``jax.distributed.initialize()`` (see experiments/README.md);
* inside each shard the rollouts run under :func:`jax.lax.map` (``inner_batch`` > 1 vmaps
  groups of that size inside the loop). A batched ``jnp.linalg.solve`` under a plain vmap
  spread over two host CPU devices deadlocks in XLA:CPU; a loop of rollouts per shard does not;
* only a deviation curve d(t) (S+1 floats) and four diagnostics come back per run; the exact
  recovery metrics (:func:`neuromotor.studies.metrics.recovery_metrics`) are computed on the host per
  chunk, so memory stays bounded by the chunk size whatever the grid size.

The deviation of a run is measured against its unperturbed twin: the same gains without any
pulse. Twins are shared: one baseline rollout per distinct gain setting, simulated first with
the same compiled program; their joint angles ((S+1) x n floats each) are the only per-setting
arrays kept for the whole sweep.

Runs that blow up (or whose baseline does) are kept and flagged: ``diverged`` is true, the
step, time and body are recorded, and the metric columns hold NaN.

Config (``[sweep]`` table of a simulation config; the grid is the Cartesian product)::

    [sweep]
    magnitudes = {start = 0.0, stop = 800.0, num = 9}   # or a list; N (or N s for impulses)
    directions = [[0.0, 0.0, 1.0]]    # default: perturbation[0].direction
    bodies = ["Chest2"]               # default: perturbation[0].body
    starts = [1.0]                    # default: perturbation[0].start
    ks = [400.0]                      # 1/s^2; a list or {start, stop, num, log = true}
    kd = [20.0]                       # 1/s; the gains grid is ks x kd ...
    # ... or explicit gain settings instead of ks x kd:
    # [[sweep.gains]]
    # label = "feedforward + low gain"; ks = 400.0; kd = 20.0; controller = "neuromotor"  # or "pd"
    chunk = 64                        # runs per device call (rounded up to a multiple of devices)
    inner_batch = 1                   # rollouts vmapped together inside each shard's loop
    output = "out/sweep"              # folder for sweep.csv and the plots (relative to the config)
    fitted = "fit.json"               # optional: fitted (ks, kd) to mark on the gains map, or [ks, kd]

Ball-speed sweeps (issue 7): when the config has a ``[ball]`` table, ``magnitudes`` are ball
speeds (m/s) and every run is a contact rollout (:mod:`neuromotor.physics.contact`) of that ball at that
speed; its twin is the same gains with the ball never launched. A ball aimed at ``ball.target``
is re-aimed for every speed, so each row equals ``neuromotor simulate`` of the config with
``ball.speed`` set to the row's magnitude. ``bodies``, ``directions`` and ``starts`` do not
apply (the aim and launch time come from ``[ball]``), and the config may not also hold
``[[perturbation]]`` tables. The gains grid, ``chunk``, ``inner_batch``, ``output`` and
``fitted`` work as for pulses. The table gets ``kind = "ball"``, the peak contact impulse on
the character and the body that received it (:data:`BALL_COLUMNS`).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import math
import pathlib
from typing import Any, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
from jaxtyping import Array, Float, Int

from neuromotor.io.atomic import atomic_path
from neuromotor.studies import metrics as mx
from neuromotor.config import ConfigError, SimulationConfig, _Fields, read_toml, simulation_config
from neuromotor.physics.control import Gains, pd_tracking_gains
from neuromotor.physics.dynamics import Reference, SimConfig, rollout
from neuromotor.physics.perturbation import ForcePulses
from neuromotor.model.skeleton import Model
from neuromotor import compiler
from neuromotor.physics import contact as ct

AXIS = "runs"
CONTROLLERS = ("neuromotor", "pd")
METRIC_KEYS = ("peak_deviation_deg", "time_of_peak_s", "recovery_time_s", "final_error_deg",
               "overshoot_deg", "recovery_threshold_deg")
COLUMNS = ("run", "label", "controller", "ks", "kd", "body", "magnitude", "direction_x", "direction_y",
           "direction_z", "start", "duration", *METRIC_KEYS, "max_kkt_residual",
           "max_constraint_violation", "diverged", "diverged_step", "diverged_time_s", "diverged_body")
# Ball-speed sweeps: magnitude = speed (m/s), direction = launch direction (re-aimed per speed when
# the ball has a target), body = the target ("" without one), start = launch time; outputs add the
# peak contact impulse on the character (N s), the body that received it and the first contact.
BALL_COLUMNS = ("run", "kind", "label", "controller", "ks", "kd", "body", "magnitude", "direction_x",
                "direction_y", "direction_z", "start", *METRIC_KEYS, "peak_impulse_Ns", "hit_body",
                "first_contact_s", "max_kkt_residual", "max_constraint_violation", "diverged", "diverged_step",
                "diverged_time_s", "diverged_body")


# ----------------------------------------------------------------------------- the grid


@dataclasses.dataclass(frozen=True)
class GainSetting:
    """One controller: the paper's model ("neuromotor") or the high-gain PD tracker ("pd")."""

    ks: float
    kd: float
    controller: str = "neuromotor"
    label: str = ""

    @property
    def name(self) -> str:
        return self.label or f"{self.controller} ks={self.ks:g} kd={self.kd:g}"


@dataclasses.dataclass
class SweepSpec:
    """The grid: every combination of gain setting, body, direction, start and magnitude."""

    magnitudes: list[float]
    gains: list[GainSetting]
    bodies: list[str] | None = None  # None: the config's perturbation[0] value
    directions: list[list[float]] | None = None
    starts: list[float] | None = None
    chunk: int = 64
    inner_batch: int = 1
    output: pathlib.Path | None = None
    fitted: tuple[float, float] | None = None
    kind: str = "force"  # "ball": magnitudes are ball speeds (m/s) of the config's [ball]

    def runs(self, base: dict) -> list[dict]:
        """Flat list of run descriptions (dicts), gain setting outermost, magnitude innermost."""
        out = []
        for g in self.gains:
            for body in self.bodies or [base["body"]]:
                for d in self.directions or [base["direction"]]:
                    for start in self.starts or [base["start"]]:
                        for m in self.magnitudes:
                            out.append(dict(gain=g, body=body, direction=list(d), start=float(start),
                                            magnitude=float(m), duration=base["duration"]))
        return out


class RunBatch(eqx.Module):
    """Inputs of a batch of runs: every leaf has a leading run axis."""

    gains: Gains
    pulses: ForcePulses


class RunOut(eqx.Module):
    """What a rollout leaves behind in a sweep (per run)."""

    theta: Float[Array, "S1 n"]
    diverged_step: Int[Array, ""]
    diverged_body: Int[Array, ""]
    max_residual: Float[Array, ""]
    max_violation: Float[Array, ""]


def gains_for(template: Gains, setting: GainSetting) -> Gains:
    g = template if setting.controller == "neuromotor" else pd_tracking_gains(template)
    return dataclasses.replace(g, ks=jnp.asarray(setting.ks, g.ks.dtype), kd=jnp.asarray(setting.kd, g.kd.dtype))


def _stack(trees: Sequence[Any]):
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def build_batch(template_gains: Gains, template_pulses: ForcePulses, runs: list[dict], body_index) -> RunBatch:
    """Batched gains and pulses for ``runs``; the grid overrides pulse 0 of the template."""
    if template_pulses.count == 0:
        raise ValueError("a sweep needs at least one [[perturbation]] to vary")
    settings = {}
    for r in runs:
        settings.setdefault(r["gain"], gains_for(template_gains, r["gain"]))
    gains = _stack([settings[r["gain"]] for r in runs])
    p = jax.tree_util.tree_map(np.asarray, template_pulses)
    n = len(runs)
    tile = lambda a: np.repeat(a[None], n, axis=0).copy()
    body, direction, mag, start = tile(p.body), tile(p.direction), tile(p.magnitude), tile(p.start)
    for i, r in enumerate(runs):
        d = np.asarray(r["direction"], np.float64)
        body[i, 0] = body_index(r["body"])
        direction[i, 0] = d / np.linalg.norm(d)
        mag[i, 0] = r["magnitude"]
        start[i, 0] = r["start"]
    pulses = ForcePulses(body, tile(p.point), direction, mag, start, tile(p.duration), p.shape)
    return RunBatch(gains, pulses)


def gain_keys(batch: RunBatch) -> tuple[np.ndarray, np.ndarray]:
    """Index of the first run with identical gains (the baseline to share) and each run's slot."""
    leaves = [np.asarray(x).reshape(len(np.asarray(batch.pulses.magnitude)), -1)
              for x in jax.tree_util.tree_leaves(batch.gains)]
    flat = np.concatenate(leaves, axis=1)
    _, first, slot = np.unique(flat, axis=0, return_index=True, return_inverse=True)
    return first, slot.reshape(-1)


# ----------------------------------------------------------------------------- sharded execution


def device_mesh(devices=None) -> Mesh:
    """A 1-D mesh over ``devices`` (default: every device of every process)."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.array(devices), (AXIS,))


def _put(x, mesh: Mesh, spec: P):
    """A global array from host data that every process holds in full (works multi-host)."""
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, NamedSharding(mesh, spec), lambda idx: x[idx])


def _gather(x) -> np.ndarray:
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


class Sweeper:
    """Compiled chunk runner for one model, reference and step configuration.

    ``run_chunk(batch)`` simulates ``chunk`` runs (a :class:`RunBatch` padded to ``chunk``)
    sharded over ``mesh``; build it once and reuse it: every call with the same chunk size
    reuses the compiled program.
    """

    def __init__(self, model: Model, ref: Reference, sim: SimConfig, *, chunk: int = 64,
                 inner_batch: int = 1, mesh: Mesh | None = None):
        self.mesh = device_mesh() if mesh is None else mesh
        n_dev = self.mesh.devices.size
        self.chunk = max(n_dev, int(math.ceil(chunk / n_dev)) * n_dev)
        self.inner_batch = max(1, min(int(inner_batch), self.chunk // n_dev))
        self.sim, self.n_steps = sim, sim.n_steps
        self.model_static = eqx.partition(model, eqx.is_array)[1]
        rep = P()
        shared = (eqx.partition(model, eqx.is_array)[0], ref)
        self.shared = jax.tree_util.tree_map(lambda x: _put(x, self.mesh, rep), shared)
        self._simulate = compiler.jit(jax.shard_map(
            self._local, mesh=self.mesh, in_specs=(rep, P(AXIS)), out_specs=P(AXIS), check_vma=False))

    def _one(self, shared, run: RunBatch) -> RunOut:
        model = eqx.combine(shared[0], self.model_static)
        r = rollout(model, run.gains, run.pulses, shared[1], self.sim)
        return RunOut(r.theta, r.diverged_step, r.diverged_body, jnp.max(r.residual), jnp.max(r.violation))

    def _local(self, shared, batch: RunBatch) -> RunOut:
        size = None if self.inner_batch == 1 else self.inner_batch
        return jax.lax.map(functools.partial(self._one, shared), batch, batch_size=size)

    def pad(self, batch: RunBatch, lo: int, hi: int) -> RunBatch:
        """Rows lo:hi of a host batch, padded to the chunk size by repeating the last row."""
        idx = np.minimum(np.arange(lo, lo + self.chunk), hi - 1)
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[idx], batch)

    def simulate_chunk(self, batch: RunBatch) -> RunOut:
        """Device-resident outputs of one padded chunk (sharded along the run axis)."""
        placed = jax.tree_util.tree_map(lambda x: _put(x, self.mesh, P(AXIS)), batch)
        return self._simulate(self.shared, placed)


@jax.jit
def _chunk_deviation(theta, base_theta, slot):
    return jax.vmap(mx.deviation)(theta, base_theta[slot])


# ----------------------------------------------------------------------------- the sweep


@dataclasses.dataclass
class SweepResult:
    rows: list[dict]  # one per run: inputs, metrics, diagnostics (COLUMNS)
    curves: np.ndarray | None  # (N, S+1) deviation curves, if kept
    time: np.ndarray  # (S+1,) clip time of the samples


def _simulate_baselines(sweeper, base_batch, n_base: int, bar):
    """Unperturbed twin runs (one per gain setting), in chunks: their theta and diverged step."""
    theta, bad = [], []
    for lo in range(0, n_base, sweeper.chunk):
        hi = min(lo + sweeper.chunk, n_base)
        out = sweeper.simulate_chunk(sweeper.pad(base_batch, lo, hi))
        theta.append(_gather(out.theta)[: hi - lo])
        bad.append(_gather(out.diverged_step)[: hi - lo])
        bar.update(hi - lo)
    return jnp.asarray(np.concatenate(theta)), np.concatenate(bad)


def run_sweep(sweeper: Sweeper, gains: Gains, pulses: ForcePulses, runs: list[dict], body_index,
              body_names: Sequence[str], *, keep_curves: bool = False, progress: bool = True) -> SweepResult:
    """Simulate every run of ``runs`` (from :meth:`SweepSpec.runs`) and measure its recovery."""
    from tqdm.auto import tqdm

    batch = build_batch(gains, pulses, runs, body_index)
    n = len(runs)
    first, slot = gain_keys(batch)
    time = np.asarray(sweeper.shared[1].time)[: sweeper.n_steps + 1]
    # Baselines: the distinct gain settings without any pulse, simulated with the same program.
    base_batch = jax.tree_util.tree_map(lambda x: np.asarray(x)[first], batch)
    base_batch = dataclasses.replace(
        base_batch, pulses=dataclasses.replace(base_batch.pulses, magnitude=np.zeros_like(base_batch.pulses.magnitude)))
    n_base, c = len(first), sweeper.chunk
    bar = tqdm(total=n_base + n, desc="sweep", unit="run", disable=not progress)
    base_theta_arr, base_step = _simulate_baselines(sweeper, base_batch, n_base, bar)
    rows, curves = [], []
    starts = np.asarray(batch.pulses.start)
    for lo in range(0, n, c):
        hi = min(lo + c, n)
        out = sweeper.simulate_chunk(sweeper.pad(batch, lo, hi))
        slot_c = np.minimum(np.arange(lo, lo + c), hi - 1)
        dev = _gather(_chunk_deviation(out.theta, base_theta_arr, jnp.asarray(slot[slot_c])))[: hi - lo]
        step = _gather(out.diverged_step)[: hi - lo]
        bad_body = _gather(out.diverged_body)[: hi - lo]
        resid = _gather(out.max_residual)[: hi - lo]
        viol = _gather(out.max_violation)[: hi - lo]
        for j in range(hi - lo):
            i = lo + j
            r = runs[i]
            g: GainSetting = r["gain"]
            d = np.asarray(r["direction"], float)
            d = d / np.linalg.norm(d)
            row = {"run": i, "label": g.name, "controller": g.controller, "ks": g.ks, "kd": g.kd,
                   "body": r["body"], "magnitude": r["magnitude"], "direction_x": float(d[0]),
                   "direction_y": float(d[1]), "direction_z": float(d[2]), "start": r["start"], "duration": r["duration"]}
            row.update(mx.recovery_metrics(time, dev[j], float(starts[i].min())))
            row["max_kkt_residual"] = float(resid[j])
            row["max_constraint_violation"] = float(viol[j])
            bstep = int(base_step[slot[i]])
            s_run = int(step[j])
            if s_run >= 0 or bstep >= 0:
                # Keep the run, flag it, and blank metrics that a frozen blown-up state would fake.
                s = s_run if s_run >= 0 else bstep
                row.update({k: float("nan") for k in METRIC_KEYS})
                row.update(diverged=True, diverged_step=s, diverged_time_s=float(time[min(s + 1, len(time) - 1)]),
                           diverged_body=body_names[int(bad_body[j])] if s_run >= 0 else "baseline")
            else:
                row.update(diverged=False, diverged_step=-1, diverged_time_s=float("nan"), diverged_body="")
            rows.append(row)
        if keep_curves:
            curves.append(dev)
        bar.update(hi - lo)
    bar.close()
    return SweepResult(rows, np.concatenate(curves) if keep_curves else None, time)


# ----------------------------------------------------------------------------- ball-speed sweeps


class BallBatch(eqx.Module):
    """Inputs of a batch of ball runs: every leaf has a leading run axis."""

    gains: Gains
    ball: ct.Ball


class BallRunOut(eqx.Module):
    """What a contact rollout leaves behind in a sweep (per run)."""

    theta: Float[Array, "S1 n"]
    diverged_step: Int[Array, ""]
    diverged_body: Int[Array, ""]  # n_bodies: the ball
    max_residual: Float[Array, ""]
    max_violation: Float[Array, ""]
    peak_impulse: Float[Array, ""]  # largest |impulse| of one step on a body of the character (N s)
    hit_body: Int[Array, ""]  # the body that received it; -1: the ball never touched the character
    first_contact: Int[Array, ""]  # first sample with a contact on the character; -1: none


class BallSweeper(Sweeper):
    """:class:`Sweeper` of contact rollouts: runs are (gains, ball) pairs, the capsules, contact
    settings and (empty) force pulses are shared by all of them."""

    def __init__(self, model: Model, ref: Reference, sim: SimConfig, ball_setup: ct.BallSetup,
                 pulses: ForcePulses, **kw):
        self.capsules, self.settings, self.pulses = ball_setup.capsules, ball_setup.settings, pulses
        super().__init__(model, ref, sim, **kw)

    def _one(self, shared, run: BallBatch) -> BallRunOut:
        model = eqx.combine(shared[0], self.model_static)
        r = ct.contact_rollout(model, run.gains, self.pulses, shared[1], self.sim, run.ball, self.capsules,
                               self.settings)
        bodies = ct.candidate_bodies(self.capsules, self.settings)
        on_char = bodies >= 0  # not the ground
        imp = jnp.linalg.norm(r.contact.impulse, axis=-1) * on_char  # (S+1, C)
        peak = jnp.max(imp)
        cand = jnp.argmax(jnp.max(imp, axis=0))
        touched = jnp.any((r.contact.normal_impulse > 0) & on_char, axis=-1)
        return BallRunOut(r.run.theta, r.run.diverged_step, r.run.diverged_body, jnp.max(r.run.residual),
                          jnp.max(r.run.violation), peak, jnp.where(peak > 0, bodies[cand], -1),
                          jnp.where(jnp.any(touched), jnp.argmax(touched), -1))


def run_ball_sweep(sweeper: BallSweeper, setup, speeds: Sequence[float], gain_settings: Sequence[GainSetting], *,
                   balls: ct.Ball | None = None, keep_curves: bool = False, progress: bool = True) -> SweepResult:
    """Contact rollouts of the config's ball at every speed x gain setting (gain setting
    outermost), chunked like :func:`run_sweep`, measured against the ball never launched.
    ``balls``: :func:`neuromotor.physics.contact.balls_at_speeds` of ``speeds``, if already built."""
    from tqdm.auto import tqdm

    spec, model = setup.config.ball, setup.model
    body_names = model.body_names
    speeds = [float(v) for v in speeds]
    if balls is None:
        balls = ct.balls_at_speeds(setup, speeds)  # (n_speeds,) leaves
    runs = [(g, i) for g in gain_settings for i in range(len(speeds))]
    n = len(runs)
    settings = {g: gains_for(setup.gains, g) for g in gain_settings}
    gains = _stack([settings[g] for g, _ in runs])
    take = np.array([i for _, i in runs])
    batch = BallBatch(gains, jax.tree_util.tree_map(lambda x: np.asarray(x)[take], balls))
    slot = np.array([list(settings).index(g) for g, _ in runs])
    # Twins: one per gain setting, the ball never launched (no contact, no force at all).
    base_batch = BallBatch(_stack(list(settings.values())),
                           _stack([ct.never_launched(setup.ball.ball)] * len(settings)))
    time = np.asarray(sweeper.shared[1].time)[: sweeper.n_steps + 1]
    launch = float(setup.ball.ball.launch)
    n_base, c = len(settings), sweeper.chunk
    bar = tqdm(total=n_base + n, desc="ball sweep", unit="run", disable=not progress)
    base_theta_arr, base_step = _simulate_baselines(sweeper, base_batch, n_base, bar)
    direction = np.asarray(batch.ball.direction)
    rows, curves = [], []
    for lo in range(0, n, c):
        hi = min(lo + c, n)
        out = sweeper.simulate_chunk(sweeper.pad(batch, lo, hi))
        slot_c = np.minimum(np.arange(lo, lo + c), hi - 1)
        dev = _gather(_chunk_deviation(out.theta, base_theta_arr, jnp.asarray(slot[slot_c])))[: hi - lo]
        host = {k: _gather(getattr(out, k))[: hi - lo] for k in (
            "diverged_step", "diverged_body", "max_residual", "max_violation", "peak_impulse", "hit_body",
            "first_contact")}
        for j in range(hi - lo):
            i = lo + j
            g, k = runs[i]
            hit, first = int(host["hit_body"][j]), int(host["first_contact"][j])
            row = {"run": i, "kind": "ball", "label": g.name, "controller": g.controller, "ks": g.ks, "kd": g.kd,
                   "body": spec.get("target", ""), "magnitude": speeds[k], "direction_x": float(direction[i, 0]),
                   "direction_y": float(direction[i, 1]), "direction_z": float(direction[i, 2]), "start": launch}
            row.update(mx.recovery_metrics(time, dev[j], launch))
            row.update(peak_impulse_Ns=float(host["peak_impulse"][j]), hit_body=body_names[hit] if hit >= 0 else "",
                       first_contact_s=float(time[first]) if first >= 0 else float("nan"),
                       max_kkt_residual=float(host["max_residual"][j]),
                       max_constraint_violation=float(host["max_violation"][j]))
            s_run, bstep = int(host["diverged_step"][j]), int(base_step[slot[i]])
            if s_run >= 0 or bstep >= 0:
                s = s_run if s_run >= 0 else bstep
                b = int(host["diverged_body"][j])
                row.update({key: float("nan") for key in METRIC_KEYS})
                row.update(diverged=True, diverged_step=s, diverged_time_s=float(time[min(s + 1, len(time) - 1)]),
                           diverged_body=("baseline" if s_run < 0 else body_names[b] if b < len(body_names)
                                          else "ball"))
            else:
                row.update(diverged=False, diverged_step=-1, diverged_time_s=float("nan"), diverged_body="")
            rows.append(row)
        if keep_curves:
            curves.append(dev)
        bar.update(hi - lo)
    bar.close()
    return SweepResult(rows, np.concatenate(curves) if keep_curves else None, time)


# ----------------------------------------------------------------------------- config


def _number_list(f: _Fields, key: str, default, *, positive=False, nonneg=False, allow_range=True):
    val = f.get(key, default)
    if val is None:
        return None
    if isinstance(val, dict) and allow_range:
        r = _Fields(val, f"{f._name(key)}", f.source)
        start = r.number("start", None)
        stop = r.number("stop", None)
        num = r.get("num", None)
        log = r.boolean("log", False)
        r.done()
        if start is None or stop is None:
            f.fail(key, "needs start and stop")
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            r.fail("num", f"must be a positive integer, got {num!r}")
        if log and not (start > 0 and stop > 0):
            f.fail(key, "log spacing needs start > 0 and stop > 0")
        vals = list(np.geomspace(start, stop, num) if log else np.linspace(start, stop, num))
    elif isinstance(val, list) and val and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in val):
        vals = [float(x) for x in val]
    else:
        f.fail(key, f"must be a non-empty list of numbers{' or {start, stop, num}' if allow_range else ''}, got {val!r}")
    if positive and any(v <= 0 for v in vals):
        f.fail(key, "values must be > 0")
    if nonneg and any(v < 0 for v in vals):
        f.fail(key, "values must be >= 0")
    return [float(v) for v in vals]


def _positive_int(f: _Fields, key: str, default: int) -> int:
    val = f.get(key, default)
    if isinstance(val, bool) or not isinstance(val, int) or val < 1:
        f.fail(key, f"must be a positive integer, got {val!r}")
    return int(val)


def read_fitted(value, source: str = "fitted") -> tuple[float, float]:
    """(ks, kd) from ``[ks, kd]`` or a JSON file holding ``ks`` and ``kd`` (at any nesting)."""
    if isinstance(value, (list, tuple)) and len(value) == 2:
        return float(value[0]), float(value[1])
    path = pathlib.Path(value)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        raise ConfigError(f"{source}: cannot read the fitted gains from {path}: {e}") from None

    def find(d):
        if isinstance(d, dict):
            if isinstance(d.get("ks"), (int, float)) and isinstance(d.get("kd"), (int, float)):
                return float(d["ks"]), float(d["kd"])
            for v in d.values():
                hit = find(v)
                if hit:
                    return hit
        return None

    hit = find(data)
    if hit is None:
        raise ConfigError(f"{source}: {path} holds no numeric 'ks' and 'kd'")
    return hit


def sweep_spec(data: dict, cfg: SimulationConfig, base_dir=None) -> SweepSpec:
    """The ``[sweep]`` table of a config (see the module docstring)."""
    source = cfg.source
    f = _Fields(data.get("sweep", {}), "sweep", source)
    kind = "force"
    if cfg.ball is not None:
        kind = "ball"
        if cfg.perturbations:
            raise ConfigError(f"{source}: field 'perturbation': a sweep of a [ball] config varies the ball speed "
                              "(sweep.magnitudes in m/s); remove the [[perturbation]] tables, or the [ball] "
                              "table to sweep the force pulse")
        for key in ("bodies", "directions", "starts"):
            if key in f.table:
                f.fail(key, "does not apply to a ball sweep: sweep.magnitudes are ball speeds (m/s); "
                            "aim and launch time come from [ball]")
        ball = cfg.ball
        speed = float(np.linalg.norm(ball["velocity"])) if "velocity" in ball else ball["speed"]
        mags = _number_list(f, "magnitudes", [speed], nonneg=True)
        if "target" in ball and any(m <= 0 for m in mags):
            f.fail("magnitudes", "ball speeds must be > 0 when the ball aims at a target (ball.target)")
    elif not cfg.perturbations:
        raise ConfigError(f"{source}: field 'perturbation' is required: a sweep varies perturbation[0] "
                          "(or give a [ball] table to sweep the ball speed)")
    else:
        base = cfg.perturbations[0]
        mags = _number_list(f, "magnitudes", [base["magnitude"]], nonneg=True)
    starts = _number_list(f, "starts", None, nonneg=True, allow_range=False)
    bodies = f.get("bodies", None)
    if bodies is not None and (not isinstance(bodies, list) or not bodies or not all(isinstance(b, str) for b in bodies)):
        f.fail("bodies", f"must be a non-empty list of body names, got {bodies!r}")
    directions = f.get("directions", None)
    if directions is not None:
        ok = isinstance(directions, list) and directions and all(
            isinstance(d, list) and len(d) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in d)
            and any(d) for d in directions)
        if not ok:
            f.fail("directions", f"must be a non-empty list of non-zero [x, y, z], got {directions!r}")
    explicit = f.get("gains", None)
    ks = _number_list(f, "ks", [cfg.ks], nonneg=True)
    kd = _number_list(f, "kd", [cfg.kd], nonneg=True)
    gains: list[GainSetting] = []
    if explicit is not None:
        if "ks" in f.table or "kd" in f.table:
            f.fail("gains", "give either [[sweep.gains]] tables or ks/kd lists, not both")
        if not isinstance(explicit, list) or not explicit:
            f.fail("gains", "must be an array of tables ([[sweep.gains]])")
        for i, t in enumerate(explicit):
            g = _Fields(t, f"sweep.gains[{i}]", source)
            gains.append(GainSetting(g.number("ks", cfg.ks, nonneg=True), g.number("kd", cfg.kd, nonneg=True),
                                     g.choice("controller", "neuromotor", CONTROLLERS), str(g.get("label", ""))))
            g.done()
    else:
        gains = [GainSetting(a, b) for a in ks for b in kd]
    chunk = _positive_int(f, "chunk", 64)
    inner = _positive_int(f, "inner_batch", 1)
    out = f.get("output", None)
    if out is not None and not isinstance(out, str):
        f.fail("output", f"must be a path string, got {out!r}")
    fitted = f.get("fitted", None)
    fitted_pair = None
    if fitted is not None:
        if isinstance(fitted, str):
            p = pathlib.Path(fitted)
            if base_dir is not None and not p.is_absolute():
                p = pathlib.Path(base_dir) / p
            fitted_pair = read_fitted(str(p), f"{source}: field 'sweep.fitted'")
        elif isinstance(fitted, list) and len(fitted) == 2 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in fitted):
            fitted_pair = read_fitted(fitted)
        else:
            f.fail("fitted", f"must be a JSON path or [ks, kd], got {fitted!r}")
    f.done()
    output = None
    if out is not None:
        output = pathlib.Path(out)
        if base_dir is not None and not output.is_absolute():
            output = (pathlib.Path(base_dir) / output).resolve()
    return SweepSpec(mags, gains, bodies, [list(map(float, d)) for d in directions] if directions else None,
                     starts, chunk, inner, output, fitted_pair, kind)


def load_sweep_config(path) -> tuple[SimulationConfig, SweepSpec]:
    path = pathlib.Path(path)
    data = read_toml(path)
    cfg = simulation_config(data, str(path), path.parent)
    return cfg, sweep_spec(data, cfg, path.parent)


# ----------------------------------------------------------------------------- outputs


def _atomic_write(path: pathlib.Path, write, mode: str = "w"):
    path = pathlib.Path(path)
    with atomic_path(path) as tmp, open(tmp, mode, **({"newline": ""} if "b" not in mode else {})) as fh:
        write(fh)
    return path


def write_csv(rows: list[dict], path, columns: Sequence[str] = COLUMNS) -> pathlib.Path:
    """One row per run (``columns``: COLUMNS, or BALL_COLUMNS for a ball-speed sweep), written
    through a temporary file and renamed."""

    def write(fh):
        w = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(float(v)) if isinstance(v, (float, np.floating)) else v) for k, v in r.items()})

    return _atomic_write(path, write)


def read_csv(path) -> list[dict]:
    """Rows of :func:`write_csv`, numbers parsed back."""
    ints = {"run", "diverged_step"}
    text = {"label", "controller", "body", "diverged_body", "kind", "hit_body"}
    out = []
    with open(path, newline="", encoding="utf-8") as fh:
        for r in csv.DictReader(fh):
            row = {}
            for k, v in r.items():
                if k in text:
                    row[k] = v
                elif k == "diverged":
                    row[k] = v == "True"
                elif k in ints:
                    row[k] = int(v)
                else:
                    row[k] = float(v)
            out.append(row)
    return out


def save_figure(fig, path) -> pathlib.Path:
    """Save a matplotlib figure as PNG through a temporary file."""
    import matplotlib.pyplot as plt

    out = _atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=fig.dpi), "wb")
    plt.close(fig)
    return out


def _series_key(r: dict) -> tuple:
    if r.get("kind") == "ball":  # an aimed ball's direction changes with its speed: one series
        return (r["label"], r["body"], 0.0, 0.0, 0.0, r["start"])
    return (r["label"], r["body"], r["direction_x"], r["direction_y"], r["direction_z"], r["start"])


def plot_sweep(rows: list[dict], path, title: str = "", xlabel: str | None = None) -> pathlib.Path:
    """Peak deviation and recovery time against magnitude, one line per gain setting (and per
    body / direction / start when those vary too). Diverged runs: red crosses on the axis.
    ``xlabel`` defaults to the pulse magnitude, or the ball speed for ball rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(_series_key(r), []).append(r)
    varying = [len({k[i] for k in groups}) > 1 for i in range(6)]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=90)
    for key, rs in groups.items():
        rs = sorted(rs, key=lambda r: r["magnitude"])
        parts = [key[0]] if varying[0] or not any(varying) else []
        if varying[1]:
            parts.append(key[1])
        if any(varying[2:5]):
            parts.append(f"dir ({key[2]:.2g}, {key[3]:.2g}, {key[4]:.2g})")
        if varying[5]:
            parts.append(f"t={key[5]:g}s")
        label = ", ".join(parts)
        m = np.array([r["magnitude"] for r in rs])
        bad = np.array([r["diverged"] for r in rs])
        for ax, col in zip(axes, ("peak_deviation_deg", "recovery_time_s")):
            y = np.array([r[col] for r in rs], float)
            line, = ax.plot(m[~bad], y[~bad], "o-", ms=3, label=label)
            # Runs still outside the recovery band at the window's end: open triangles on top.
            late = ~bad & ~np.isfinite(y)
            if late.any():
                ax.plot(m[late], np.ones(late.sum()), "^", mfc="none", color=line.get_color(), ms=7,
                        clip_on=False, transform=ax.get_xaxis_transform())
            if bad.any():
                ax.plot(m[bad], np.zeros(bad.sum()), "x", color="red", ms=7, clip_on=False,
                        transform=ax.get_xaxis_transform(), label="diverged" if ax is axes[0] else None)
    if xlabel is None:
        xlabel = "ball speed (m/s)" if rows and rows[0].get("kind") == "ball" else "pulse magnitude (N)"
    axes[0].set(xlabel=xlabel, ylabel="peak deviation (deg)")
    axes[1].set(xlabel=xlabel, ylabel="recovery time (s)")
    axes[1].set_title("open triangle: not recovered by the window's end; red x: diverged", fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_gains_map(rows: list[dict], path, fitted: tuple[float, float] | None = None, title: str = "") -> pathlib.Path:
    """Heat maps of recovery time and peak deviation over the (ks, kd) grid of one hit.

    Cells whose run diverged (or never recovered) are grey with a cross; the fitted pair is a
    white star."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = np.array(sorted({r["ks"] for r in rows}))
    kd = np.array(sorted({r["kd"] for r in rows}))
    grid = {(r["ks"], r["kd"]): r for r in rows}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=90)

    def edges(v):
        if len(v) == 1:
            return np.array([v[0] * 0.8, v[0] * 1.25])
        lv = np.log(v)
        mid = 0.5 * (lv[1:] + lv[:-1])
        return np.exp(np.concatenate([[2 * lv[0] - mid[0]], mid, [2 * lv[-1] - mid[-1]]]))

    for ax, col, name in zip(axes, ("recovery_time_s", "peak_deviation_deg"), ("recovery time (s)", "peak deviation (deg)")):
        z = np.full((len(kd), len(ks)), np.nan)
        bad = np.zeros_like(z, bool)
        late = np.zeros_like(z, bool)
        for i, b in enumerate(kd):
            for j, a in enumerate(ks):
                r = grid.get((a, b))
                if r is not None:
                    z[i, j] = r[col]
                    bad[i, j] = bool(r["diverged"])
                    late[i, j] = not bad[i, j] and not np.isfinite(r[col])
        cmap = plt.get_cmap("viridis").with_extremes(bad="0.7")
        mesh = ax.pcolormesh(edges(ks), edges(kd), np.ma.masked_invalid(z), cmap=cmap, shading="flat")
        fig.colorbar(mesh, ax=ax, label=name)
        yy, xx = np.nonzero(bad)
        if len(xx):
            ax.plot(ks[xx], kd[yy], "x", color="red", ms=6, label="diverged")
        yy, xx = np.nonzero(late)
        if len(xx):
            ax.plot(ks[xx], kd[yy], "o", mfc="none", color="black", ms=5, label="not recovered in the window")
        if fitted is not None:
            ax.plot([fitted[0]], [fitted[1]], "*", color="white", mec="black", ms=16, label="fitted (ks, kd)")
        ax.set(xscale="log", yscale="log", xlabel="ks (1/s$^2$)", ylabel="kd (1/s)", title=name)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="upper left")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


# ----------------------------------------------------------------------------- entry point


def sweep_from_config(path, output=None, *, devices=None, chunk=None, inner_batch=None, fitted=None,
                      progress: bool = True) -> tuple[SweepResult, dict[str, pathlib.Path]]:
    """Run the sweep of a config file; write ``sweep.csv``, ``sweep.png`` and, when ks and kd
    both vary, ``gains_map.png`` into ``output`` (default: the config's ``sweep.output``).
    A config with a ``[ball]`` table sweeps the ball speed (see the module docstring)."""
    from neuromotor.studies.simulate import body_lookup, prepare

    cfg, spec = load_sweep_config(path)
    out = pathlib.Path(output or spec.output or pathlib.Path("out") / "sweep" / pathlib.Path(path).stem)
    if fitted is not None:
        spec.fitted = read_fitted(fitted, "--fitted")
    setup = prepare(cfg)
    model = setup.model
    lead = jax.process_index() == 0  # with several hosts, every process computes, one writes
    mesh = None if devices is None else device_mesh(devices)
    if spec.kind == "ball":
        # Aim every speed first: a speed that cannot reach the target is a config error.
        try:
            balls = ct.balls_at_speeds(setup, spec.magnitudes)
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(f"{cfg.source}: field 'sweep.magnitudes': {e}") from None
        sweeper = BallSweeper(model, setup.ref, setup.sim, setup.ball, setup.pulses, chunk=chunk or spec.chunk,
                              inner_batch=inner_batch or spec.inner_batch, mesh=mesh)
        result = run_ball_sweep(sweeper, setup, spec.magnitudes, spec.gains, balls=balls, progress=progress and lead)
    else:
        index = body_lookup(model, f"{cfg.source}: field 'sweep.bodies'")
        for b in spec.bodies or []:
            index(b)
        sweeper = Sweeper(model, setup.ref, setup.sim, chunk=chunk or spec.chunk,
                          inner_batch=inner_batch or spec.inner_batch, mesh=mesh)
        runs = spec.runs(cfg.perturbations[0])
        result = run_sweep(sweeper, setup.gains, setup.pulses, runs, index, model.body_names,
                           progress=progress and lead)
    if not lead:
        return result, {}
    files = {"csv": write_csv(result.rows, out / "sweep.csv", BALL_COLUMNS if spec.kind == "ball" else COLUMNS)}
    name = pathlib.Path(path).stem
    if len(spec.magnitudes) > 1:
        files["plot"] = plot_sweep(result.rows, out / "sweep.png", title=name)
    if len({g.ks for g in spec.gains}) > 1 and len({g.kd for g in spec.gains}) > 1:
        if len(spec.magnitudes) == 1 and spec.kind == "ball":
            aim = f"at {cfg.ball['target']}" if "target" in cfg.ball else "thrown"
            name += f": {spec.magnitudes[0]:g} m/s ball {aim}, launched at {cfg.ball['launch']:g} s"
        elif len(spec.magnitudes) == 1:
            hit = cfg.perturbations[0]
            name += f": {spec.magnitudes[0]:g} N {hit['shape']} pulse on {hit['body']} at {hit['start']:g} s"
        files["gains_map"] = plot_gains_map(result.rows, out / "gains_map.png", spec.fitted, title=name)
    return result, files
