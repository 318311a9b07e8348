"""Arm experiment: the rest of the body driven along the mocap, a push at the forearm.

    .venv/bin/python experiments/arm.py [configs/exp_arm.toml] [-o DIR]

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
    ap.add_argument("config", nargs="?", default=str(_common.REPO / "configs" / "exp_arm.toml"))
    ap.add_argument("-o", "--output")
    args = ap.parse_args(argv)
    try:
        numbers = run_experiment(args.config, "arm", args.output)
    except (ConfigError, SimulationDiverged, FileNotFoundError, ValueError) as e:
        print(f"arm: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(numbers, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
