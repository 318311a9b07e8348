#!/usr/bin/env python
"""Calibrate the stiffness/damping pair (ks, kd) to a target recovery response.

    python fit/calibrate_gains.py configs/fit_synthetic.toml [-o OUTDIR] [--solver NAME]
    python fit/calibrate_gains.py configs/fit_synthetic.toml --write-synthetic KS KD [--noise-deg 0.1]

Writes OUTDIR/fit.json (gains, standard errors, residual, solver, iterations, wall time) and
OUTDIR/fit.png (target, fitted response, response at the starting gains). The same as
``neuromotor fit CONFIG.toml``; this script is a thin wrapper over neuromotor.studies.fit.
"""

import os
import pathlib
import sys

REPO = pathlib.Path(__file__).resolve().parents[1]


def _persistent_compile_cache():
    # Rollout + Jacobian compiles take minutes; reuse them across runs of this script.
    import jax

    d = os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(REPO / ".jax_cache"))
    jax.config.update("jax_compilation_cache_dir", d)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


if __name__ == "__main__":
    _persistent_compile_cache()
    from neuromotor.cli import main

    sys.exit(main(["fit"] + sys.argv[1:]))
