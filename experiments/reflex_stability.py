"""The paper's stability argument as a figure: the default hit over a grid of delayed feedback
gain x loop delay, stable cells and their recovery time, the boundary, the paper's zero-delay
low-gain muscle feedback marked (docs/reflex.md).

    .venv/bin/python experiments/reflex_stability.py configs/sweep_reflex.toml

Writes stability.csv (every cell classified), boundary.json and stability.png into the config's
sweep.output (or -o) and the figure to experiments/figures/reflex_stability.png.
"""

import argparse
import sys

import _common

from neuromotor.errors import UserError
from neuromotor.studies.reflex import STABLE_PEAK_DEG, stability_boundary, stability_from_config


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(_common.REPO / "configs" / "sweep_reflex.toml"))
    ap.add_argument("-o", "--output")
    ap.add_argument("--figure", default=str(_common.REPO / "experiments" / "figures" / "reflex_stability.png"))
    ap.add_argument("--bound", type=float, default=STABLE_PEAK_DEG, help="peak deviation (deg) of a stable run")
    ap.add_argument("--inner-batch", type=int, help="rollouts vmapped together (default: the config's)")
    args = ap.parse_args(argv)
    try:
        rows, files = stability_from_config(args.config, args.output, args.figure, bound_deg=args.bound,
                                            inner_batch=args.inner_batch)
    except (UserError, OSError) as e:
        print(f"reflex_stability: error: {e}", file=sys.stderr)
        return 2
    counts = {s: sum(r["stability"] == s for r in rows) for s in ("stable", "sustained", "large", "diverged")}
    print(f"{len(rows)} cells: " + ", ".join(f"{n} {s}" for s, n in counts.items()))
    print("| delay (ms) | largest stable gain (1/s^2) | smallest unstable gain (1/s^2) |")
    print("| --- | --- | --- |")
    for b in stability_boundary(rows):
        print(f"| {1000 * b['delay_s']:g} | {b['largest_stable_gain']} | {b['smallest_unstable_gain']} |")
    print("wrote " + ", ".join(str(f) for f in files.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
