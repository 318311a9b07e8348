"""How a run's figures depend on the time step h (the step of Eq. 2 is first order).

    .venv/bin/python experiments/step_convergence.py [CONFIG] [--steps 60 120 240 480 960 1920]

Runs CONFIG (default: configs/simulate_default.toml, the main job) at h = 1/N s for each N,
everything else as configured, and prints the recovery metrics per h, the ratio of successive
differences (about 2 when the error is first order in h) and, from the two finest steps, the
Richardson estimate of the h -> 0 limit (2 m(h/2) - m(h)) and each step's error against it.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import _common  # noqa: F401  (float64, compile cache)

from neuromotor.config.parse import load_simulation_config
from neuromotor.studies.simulate import prepare, run

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("peak_deviation_deg", "time_of_peak_s", "recovery_time_s", "overshoot_deg", "final_error_deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "simulate_default.toml"))
    ap.add_argument("--steps", type=int, nargs="+", default=[60, 120, 240, 480, 960, 1920], help="N: h = 1/N s")
    args = ap.parse_args()
    base = load_simulation_config(args.config)
    rows = []
    for n in sorted(args.steps):
        metrics = run(prepare(dataclasses.replace(base, h=1.0 / n))).metrics
        rows.append((n, [float(metrics[k]) for k in KEYS]))
        print(f"h = 1/{n:<5d}" + "".join(f"  {k} {v:9.4f}" for k, v in zip(KEYS, rows[-1][1])), flush=True)
    if len(rows) < 3:
        return
    print("ratio of successive differences (2: first order):")
    for i in range(2, len(rows)):
        ratios = []
        for j in range(len(KEYS)):
            a, b, c = rows[i - 2][1][j], rows[i - 1][1][j], rows[i][1][j]
            ratios.append((b - a) / (c - b) if c != b else float("nan"))
        print(f"  1/{rows[i - 2][0]}, 1/{rows[i - 1][0]}, 1/{rows[i][0]}:" + "".join(f" {r:6.2f}" for r in ratios))
    fine, finer = rows[-2][1], rows[-1][1]
    limit = [2.0 * b - a for a, b in zip(fine, finer)]
    print("h -> 0 (Richardson, two finest):" + "".join(f"  {k} {v:.4f}" for k, v in zip(KEYS, limit)))
    for n, values in rows:
        err = [100.0 * (v - lim) / lim if lim else float("nan") for v, lim in zip(values, limit)]
        print(f"  h = 1/{n:<5d} error against the limit (%):" + "".join(f" {e:7.1f}" for e in err))


if __name__ == "__main__":
    main()
