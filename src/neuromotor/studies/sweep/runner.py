"""Sharded execution of a sweep: chunks of runs over a 1-D device mesh, baselines first, exact
recovery metrics on the host per chunk."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from neuromotor import compiler
from neuromotor.model.skeleton import Model
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import Reference, SimConfig, rollout
from neuromotor.physics.perturbation import ForcePulses
from neuromotor.studies import metrics as mx
from neuromotor.studies.sweep.grid import METRIC_KEYS, RunBatch, RunOut, build_batch, gain_keys


AXIS = "runs"


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
    first, slot = gain_keys(batch)
    # Baselines: the distinct gain settings without any pulse, simulated with the same program.
    base = jax.tree_util.tree_map(lambda x: np.asarray(x)[first], batch)
    silent = dataclasses.replace(base.pulses, magnitude=np.zeros_like(base.pulses.magnitude))
    base = dataclasses.replace(base, pulses=silent)
    starts = np.asarray(batch.pulses.start)

    def row(i: int, out: dict, dev, time) -> dict:
        r, g = runs[i], runs[i]["gain"]
        d = np.asarray(r["direction"], float)
        d = d / np.linalg.norm(d)
        return {"run": i, "label": g.name, "controller": g.controller, "ks": g.ks, "kd": g.kd,
                "body": r["body"], "magnitude": r["magnitude"], "direction_x": float(d[0]),
                "direction_y": float(d[1]), "direction_z": float(d[2]), "start": r["start"], "duration": r["duration"],
                **mx.recovery_metrics(time, dev, float(starts[i].min())),
                "max_kkt_residual": float(out["max_residual"]), "max_constraint_violation": float(out["max_violation"])}

    bar = tqdm(total=len(first) + len(runs), desc="sweep", unit="run", disable=not progress)
    return sweep_batches(sweeper, batch, base, slot, row, lambda out: body_names[int(out["diverged_body"])], bar,
                         keep_curves)


def flag_divergence(row: dict, step: int, base_step: int, time, body) -> dict:
    """Keep a run that blew up (or whose twin did), flagged, with the metrics that a frozen
    blown-up state would fake blanked; ``body()`` names the body it blew up in."""
    if step >= 0 or base_step >= 0:
        s = step if step >= 0 else base_step
        row.update({k: float("nan") for k in METRIC_KEYS})
        row.update(diverged=True, diverged_step=s, diverged_time_s=float(time[min(s + 1, len(time) - 1)]),
                   diverged_body=body() if step >= 0 else "baseline")
    else:
        row.update(diverged=False, diverged_step=-1, diverged_time_s=float("nan"), diverged_body="")
    return row


def sweep_batches(sweeper: Sweeper, batch, base_batch, slot, make_row, body_name, bar,
                  keep_curves: bool = False) -> SweepResult:
    """Baselines first, then every run of ``batch`` in chunks: ``make_row(i, outputs, d(t), time)``
    gives run i's row, ``body_name(outputs)`` the body a diverged run blew up in."""
    n, c = len(slot), sweeper.chunk
    n_base = len(np.asarray(jax.tree_util.tree_leaves(base_batch)[0]))
    time = np.asarray(sweeper.shared[1].time)[: sweeper.n_steps + 1]
    base_theta, base_step = _simulate_baselines(sweeper, base_batch, n_base, bar)
    rows, curves = [], []
    for lo in range(0, n, c):
        hi = min(lo + c, n)
        out = sweeper.simulate_chunk(sweeper.pad(batch, lo, hi))
        slot_c = np.minimum(np.arange(lo, lo + c), hi - 1)
        dev = _gather(_chunk_deviation(out.theta, base_theta, jnp.asarray(slot[slot_c])))[: hi - lo]
        host = {f.name: _gather(getattr(out, f.name))[: hi - lo] for f in dataclasses.fields(out) if f.name != "theta"}
        for j in range(hi - lo):
            h = {k: v[j] for k, v in host.items()}
            row = make_row(lo + j, h, dev[j], time)
            rows.append(flag_divergence(row, int(h["diverged_step"]), int(base_step[slot[lo + j]]), time,
                                        lambda: body_name(h)))
        if keep_curves:
            curves.append(dev)
        bar.update(hi - lo)
    bar.close()
    return SweepResult(rows, np.concatenate(curves) if keep_curves else None, time)
