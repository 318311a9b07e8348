"""What float32 costs: one hit run in float64 and in float32 side by side.

The same clip, character, hit and gains are simulated in both precisions
(``SimulationConfig.dtype``, see :mod:`neuromotor.physics.precision`), and the recovery metrics of
Section 6 (:mod:`neuromotor.studies.metrics`) are compared with the drift diagnostics of the step:
the largest relative KKT residual of Eq. 2 and the largest constraint violation left by
post-stabilization. ``experiments/float32_check.py`` prints the table of docs/float32.md.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

from neuromotor.config import SimulationConfig
from neuromotor.physics.precision import Precision
from neuromotor.studies.simulate import RunResult, config_character, prepare, run

# The agreement float32 must keep with float64 (issue 17): peak deviation within 1 %, recovery
# time within one step.
PEAK_RTOL = 0.01
RECOVERY_STEPS = 1.0


@dataclasses.dataclass(frozen=True)
class PrecisionComparison:
    """Metrics of one hit in float64 and float32 (``metrics[Precision]``, see ``run_metrics``)."""

    name: str
    h: float
    metrics: dict  # Precision -> the run's metrics dict

    def of(self, precision: Precision | str) -> dict:
        return self.metrics[Precision(precision)]

    @property
    def peak_rel_diff(self) -> float:
        """|peak32 - peak64| / peak64."""
        p64, p32 = self.of("float64")["peak_deviation_deg"], self.of("float32")["peak_deviation_deg"]
        return abs(p32 - p64) / p64

    @property
    def recovery_diff_steps(self) -> float:
        """|recovery32 - recovery64| in steps of h; 0 when neither recovers within the window."""
        r64, r32 = self.of("float64")["recovery_time_s"], self.of("float32")["recovery_time_s"]
        if math.isnan(r64) and math.isnan(r32):
            return 0.0
        return abs(r32 - r64) / self.h  # nan when only one recovers

    @property
    def agrees(self) -> bool:
        """The issue's bounds (``PEAK_RTOL``, ``RECOVERY_STEPS``; step rounding allowed for) and
        float32 stable wherever float64 is."""
        stable = self.of("float64")["diverged"] or not self.of("float32")["diverged"]
        return stable and self.peak_rel_diff <= PEAK_RTOL and self.recovery_diff_steps <= RECOVERY_STEPS + 1e-3

    def row(self) -> dict:
        """One line of the docs/float32.md table."""
        m64, m32 = self.of("float64"), self.of("float32")
        return {
            "run": self.name,
            "h_s": self.h,
            "peak64_deg": m64["peak_deviation_deg"],
            "peak32_deg": m32["peak_deviation_deg"],
            "peak_rel_diff": self.peak_rel_diff,
            "recovery64_s": m64["recovery_time_s"],
            "recovery32_s": m32["recovery_time_s"],
            "recovery_diff_steps": self.recovery_diff_steps,
            "kkt64": m64["max_kkt_residual"],
            "kkt32": m32["max_kkt_residual"],
            "violation64": m64["max_constraint_violation"],
            "violation32": m32["max_constraint_violation"],
            "diverged64": m64["diverged"],
            "diverged32": m32["diverged"],
        }


def run_both(config: SimulationConfig) -> dict[Precision, RunResult]:
    """The config's hit run in float64 and in float32 (one character for both; no divergence
    check: divergence is part of what is compared)."""
    character, traj = config_character(config)
    return {p: run(prepare(dataclasses.replace(config, dtype=p), character, traj), check=False) for p in Precision}


def compare(config: SimulationConfig, name: str = "") -> PrecisionComparison:
    """Float32 against float64 on the config's hit (see :class:`PrecisionComparison`)."""
    results = run_both(config)
    return PrecisionComparison(name or config.source, config.h, {p: r.metrics for p, r in results.items()})


# A 300 N half-sine push on the chest for 0.1 s at t = 1 s: a segment keyword, so one hit serves
# every rig (the hit of experiments/every_clip.py and tests/studies/test_every_clip.py).
CHEST_PUSH = dict(
    kind="force",
    body="chest",
    point=None,
    direction=[1.0, 0.0, 0.0],
    magnitude=300.0,
    start=1.0,
    duration=0.1,
    shape="half_sine",
)
# Clips whose driven root turns too fast for h = 1/120 s (see studies.simulate.step_warnings).
CLIP_STEP = {"bandai_kick_22joint_6ch": 1.0 / 360.0}


def clip_config(path, duration: float = 3.0) -> SimulationConfig:
    """The chest push on a clip, at the step the clip needs."""
    h = CLIP_STEP.get(pathlib.Path(path).stem, 1.0 / 120.0)
    return SimulationConfig(
        clip=str(path),
        h=h,
        duration=duration,
        perturbations=[dict(CHEST_PUSH)],  # type: ignore[list-item]  # specs made in __post_init__
        source=pathlib.Path(path).stem,
    )


def default_hit_config() -> SimulationConfig:
    """The default hit of ``neuromotor simulate`` and ``demo``: the embedded clip, 3 s."""
    from neuromotor.config import DEFAULT_HIT

    return SimulationConfig(perturbations=[DEFAULT_HIT], duration=3.0, source="default hit")
