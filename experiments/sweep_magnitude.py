"""Sweep pulse magnitude (x gain settings): CSV table plus peak/recovery-vs-magnitude plot.

    .venv/bin/python experiments/sweep_magnitude.py configs/sweep_magnitude.toml [-o DIR]

Same as ``neuromotor sweep CONFIG``; see neuromotor.studies.sweep for the [sweep] table.
"""

import argparse
import sys

import _common  # noqa: F401  (float64, compile cache)

from neuromotor.errors import UserError
from neuromotor.studies.sweep import sweep_from_config


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(_common.REPO / "configs" / "sweep_magnitude.toml"))
    ap.add_argument("-o", "--output")
    ap.add_argument("--chunk", type=int)
    ap.add_argument("--inner-batch", type=int)
    _common.add_distributed_args(ap)
    args = ap.parse_args(argv)
    _common.init_distributed(args)
    try:
        result, files = sweep_from_config(args.config, args.output, chunk=args.chunk, inner_batch=args.inner_batch)
    except (UserError, OSError) as e:
        print(f"sweep_magnitude: error: {e}", file=sys.stderr)
        return 2
    if _common.jax.process_index() != 0:  # process 0 wrote the table and reports it
        return 0
    for r in result.rows:
        flag = f"  DIVERGED at step {r['diverged_step']} in {r['diverged_body']}" if r["diverged"] else ""
        print(f"{r['label']:<32} {r['magnitude']:8.1f} N  peak {r['peak_deviation_deg']:7.2f} deg  "
              f"recovery {r['recovery_time_s']:6.3f} s{flag}")
    print("wrote " + ", ".join(str(f) for f in files.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
