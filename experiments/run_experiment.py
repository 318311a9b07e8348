"""Run one of the paper's experiments (arm, full body, high-gain contrast) from its config.

    .venv/bin/python experiments/run_experiment.py configs/exp_arm.toml [-o DIR]

The config's ``[experiment]`` kind picks the experiment; the same as ``neuromotor experiment
CONFIG``. Writes run*.npz, metrics.json and PNG figures into the output folder (see
neuromotor.studies.experiments).
"""

import sys

import _common  # noqa: F401  (float64, compile cache)

from neuromotor.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", *sys.argv[1:]]))
