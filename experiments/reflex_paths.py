"""The default hit with muscle feedback only, with the spinal reflex, and with both delayed paths:
deviation curves and recovery metrics side by side (docs/reflex.md).

    .venv/bin/python experiments/reflex_paths.py configs/exp_reflex.toml

Writes paths.csv, paths.json and paths.png into out/reflex_paths (or -o) and the figure to
experiments/figures/reflex_paths.png.
"""

import argparse
import sys

import _common

from neuromotor.errors import UserError
from neuromotor.studies.reflex import paths_from_config


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(_common.REPO / "configs" / "exp_reflex.toml"))
    ap.add_argument("-o", "--output", default=str(_common.REPO / "out" / "reflex_paths"))
    ap.add_argument("--figure", default=str(_common.REPO / "experiments" / "figures" / "reflex_paths.png"))
    args = ap.parse_args(argv)
    try:
        comp, files = paths_from_config(args.config, args.output, args.figure)
    except (UserError, OSError) as e:
        print(f"reflex_paths: error: {e}", file=sys.stderr)
        return 2
    print("| path | peak (deg) | time to peak (s) | recovery (s) | overshoot (deg) | peak reflex (N m) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, m in comp.metrics.items():
        print(f"| {name} | {m['peak_deviation_deg']:.2f} | {m['time_to_peak_s']:.3f} | {m['recovery_time_s']:.2f} "
              f"| {m['overshoot_deg']:.2f} | {m['peak_reflex_Nm']:.1f} |")
    print("wrote " + ", ".join(str(f) for f in files.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
