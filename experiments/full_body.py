"""Full-body experiment (Figure 2): chest hit, filmstrip (original above, perturbed below) and video.

    .venv/bin/python experiments/full_body.py [configs/exp_full_body.toml] [-o DIR]

Writes run*.npz, metrics.json and PNG figures into the output folder (see neuromotor.studies.experiments).
"""

import argparse
import json
import sys

import _common  # noqa: F401

from neuromotor.config import ConfigError
from neuromotor.physics.dynamics import SimulationDiverged
from neuromotor.studies.experiments import run_experiment


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", default=str(_common.REPO / "configs" / "exp_full_body.toml"))
    ap.add_argument("-o", "--output")
    args = ap.parse_args(argv)
    try:
        numbers = run_experiment(args.config, "full_body", args.output)
    except (ConfigError, SimulationDiverged, FileNotFoundError, ValueError) as e:
        print(f"full_body: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(numbers, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
