"""Gains map: recovery time and peak deviation of one hit over a (ks, kd) grid, as heat maps.

    .venv/bin/python experiments/gains_map.py configs/sweep_gains_map.toml --fitted KS KD
    .venv/bin/python experiments/gains_map.py configs/sweep_gains_map.toml --fitted-json fit.json

The fitted pair (from the fitting layer's JSON, or given directly) is marked with a star.
"""

import argparse
import sys

import _common  # noqa: F401

from neuromotor.errors import UserError
from neuromotor.studies.sweep import sweep_from_config


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(_common.REPO / "configs" / "sweep_gains_map.toml"))
    ap.add_argument("-o", "--output")
    ap.add_argument("--fitted", type=float, nargs=2, metavar=("KS", "KD"))
    ap.add_argument("--fitted-json", help="JSON written by the fitting layer (keys ks and kd, any nesting)")
    ap.add_argument("--chunk", type=int)
    _common.add_distributed_args(ap)
    args = ap.parse_args(argv)
    _common.init_distributed(args)
    fitted = tuple(args.fitted) if args.fitted else args.fitted_json
    try:
        result, files = sweep_from_config(args.config, args.output, chunk=args.chunk, fitted=fitted)
    except (UserError, OSError) as e:
        print(f"gains_map: error: {e}", file=sys.stderr)
        return 2
    if _common.jax.process_index() != 0:  # process 0 wrote the table and reports it
        return 0
    if "gains_map" not in files:
        print("gains_map: error: the config's grid must vary both ks and kd", file=sys.stderr)
        return 2
    ok = [r for r in result.rows if not r["diverged"] and r["recovery_time_s"] == r["recovery_time_s"]]
    best = min(ok, key=lambda r: r["recovery_time_s"]) if ok else None
    print(f"{len(result.rows)} cells, {sum(r['diverged'] for r in result.rows)} diverged")
    if best:
        print(f"fastest recovery {best['recovery_time_s']:.3f} s at ks={best['ks']:.4g}, kd={best['kd']:.4g} "
              f"(peak {best['peak_deviation_deg']:.2f} deg)")
    print("wrote " + ", ".join(str(f) for f in files.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
