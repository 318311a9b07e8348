"""A platform translation under the standing character (issue 38): a base motion under a free
root moves the ground (docs/contact.md, "A moving ground"), as a posturography platform does
(Nashner 1976; Horak & Nashner 1986).

    .venv/bin/python experiments/platform_balance.py [configs/platform_balance.toml] [--magnitude 0.2]

Runs the config through ``neuromotor simulate``'s functions and prints whether it fell, and the
COM relative to the platform along the facing direction (AP, forward positive) and across it,
in mm from its value at the platform's onset: the peak forward excursion, its time, and the
offset at the end; how far the feet moved on the platform (slip or roll) and the COM over the
feet; then a line every 0.25 s. A run that blows up is cut at its last state before the blow-up.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib

import _common  # noqa: F401  (float64, compile cache)
import numpy as np

from neuromotor.config.parse import load_simulation_config
from neuromotor.studies.balance import com_path, facing_axes
from neuromotor.studies.ground import foot_bodies, platform_offset
from neuromotor.studies.simulate import prepare, run

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "platform_balance.toml"))
    ap.add_argument(
        "--magnitude", type=float, default=None, help="the platform's peak acceleration (the config's unit)"
    )
    args = ap.parse_args()
    cfg = load_simulation_config(args.config)
    if args.magnitude is not None:
        cfg = dataclasses.replace(
            cfg, perturbations=[dataclasses.replace(cfg.perturbations[0], magnitude=args.magnitude)]
        )
    setup = prepare(cfg)
    result = run(setup, check=False)  # a run that blows up is reported (diverged_s), not raised
    m = result.metrics
    model = setup.model
    _, fwd, side = facing_axes(setup)
    bad = int(result.perturbed.diverged_step)  # after a blow-up the state is held: cut there
    last = result.perturbed.time.shape[0] if bad < 0 else bad + 1
    time = np.asarray(result.perturbed.time)[:last] - float(result.perturbed.time[0])
    offset = platform_offset(setup)
    com = com_path(model, result.perturbed.states.pos[:last]) - (0.0 if offset is None else offset[: time.shape[0]])
    hit = cfg.perturbations[0]
    k0 = int(np.searchsorted(time, float(hit.start) - float(cfg.start) - 1e-9))
    rel = 1000 * (com - com[k0])
    ap_, ml = rel @ fwd, rel @ side
    k = k0 + int(np.argmax(ap_[k0:]))
    print(f"{hit.label()} {hit.place} ({hit['direction']}) at {float(hit.start):g} s, {time[-1]:g} s simulated")
    print(f"fell: {m['fell']}  fall_time_s: {m['fall_time_s']}  fall_body: {m['fall_body']!r}", end="  ")
    print(f"diverged: {m['diverged']} (diverged_s {m['diverged_s']})")
    print(f"COM relative to the platform from onset: peak forward {ap_[k]:.1f} mm at {time[k] - time[k0]:.2f} s after")
    print(f"  onset; largest backward {ap_[k0:].min():.1f} mm; at the end AP {ap_[-1]:.1f} mm, ML {ml[-1]:.1f} mm")
    if bad >= 0:
        print(f"  (the end: the last state before the blow-up, {time[-1]:.3f} s)")
    # The feet's COMs relative to the platform (a slip or a roll), and the COM relative to them.
    feet = np.asarray(result.perturbed.states.pos)[:last, list(foot_bodies(setup.character))].mean(1)
    feet = feet - (0.0 if offset is None else offset[: time.shape[0]])
    slip = 1000 * (feet - feet[k0])
    lean = rel - slip
    print(f"  feet on the platform at the end: AP {slip[-1] @ fwd:.1f} mm, ML {slip[-1] @ side:.1f} mm")
    print(f"  COM over the feet: peak forward {(lean[k0:] @ fwd).max():.1f} mm, at the end {lean[-1] @ fwd:.1f} mm")
    for i in range(k0, time.shape[0], max(1, int(round(0.25 / setup.options.h)))):
        print(
            f"  t {time[i] - time[k0]:5.2f} s  COM AP {ap_[i]:7.1f} mm  ML {ml[i]:6.1f} mm"
            f"  feet AP {slip[i] @ fwd:7.1f} mm  COM over feet AP {lean[i] @ fwd:7.1f} mm"
        )


if __name__ == "__main__":
    main()
