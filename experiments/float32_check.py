"""float32 against float64 on the default hit and on every shipped clip: the table of
docs/float32.md (peak deviation, recovery time, KKT residual, constraint violation).

    .venv/bin/python experiments/float32_check.py [CLIP.bvh ...]
"""

import argparse
import math

import _common  # noqa: F401

from neuromotor.studies.float32_compare import clip_config, compare, default_hit_config

SHARED = _common.REPO.parent / "shared" / "mocap"


def _fmt(x) -> str:
    return "-" if isinstance(x, float) and math.isnan(x) else f"{x:.4g}" if isinstance(x, float) else str(x)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("clips", nargs="*", default=sorted(str(p) for p in SHARED.glob("*.bvh")))
    args = ap.parse_args(argv)
    configs = [default_hit_config()] + [clip_config(p) for p in args.clips]
    cols = ["run", "h_s", "peak64_deg", "peak32_deg", "peak_rel_diff", "recovery64_s", "recovery32_s",
            "recovery_diff_steps", "kkt64", "kkt32", "violation64", "violation32", "diverged64", "diverged32"]
    print("| " + " | ".join(cols) + " | agrees |")
    print("|" + " --- |" * (len(cols) + 1))
    for cfg in configs:
        c = compare(cfg)
        row = c.row()
        print("| " + " | ".join(_fmt(row[k]) for k in cols) + f" | {c.agrees} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
