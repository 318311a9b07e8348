"""The grid of a sweep as a batch: one row of gains and force pulses per run, and the shared
unperturbed twin of each distinct gain setting."""

from __future__ import annotations

from typing import Any, Sequence

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.errors import ConfigError
from neuromotor.physics.control import Gains
from neuromotor.physics.perturbation import ForcePulses
from neuromotor.studies.gains import apply_gains


METRIC_KEYS = ("peak_deviation_deg", "time_of_peak_s", "recovery_time_s", "final_error_deg",
               "overshoot_deg", "recovery_threshold_deg")


COLUMNS = ("run", "label", "controller", "ks", "kd", "body", "magnitude", "direction_x", "direction_y",
           "direction_z", "start", "duration", *METRIC_KEYS, "max_kkt_residual",
           "max_constraint_violation", "diverged", "diverged_step", "diverged_time_s", "diverged_body")


BALL_COLUMNS = ("run", "kind", "label", "controller", "ks", "kd", "body", "magnitude", "direction_x",
                "direction_y", "direction_z", "start", *METRIC_KEYS, "peak_impulse_Ns", "hit_body",
                "first_contact_s", "max_kkt_residual", "max_constraint_violation", "diverged", "diverged_step",
                "diverged_time_s", "diverged_body")


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


def _stack(trees: Sequence[Any]):
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def build_batch(template_gains: Gains, template_pulses: ForcePulses, runs: list[dict], body_index) -> RunBatch:
    """Batched gains and pulses for ``runs``; the grid overrides pulse 0 of the template."""
    if template_pulses.count == 0:
        raise ConfigError("a sweep needs at least one [[perturbation]] to vary")
    settings = {}
    for r in runs:
        settings.setdefault(r["gain"], apply_gains(template_gains, r["gain"]))
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
