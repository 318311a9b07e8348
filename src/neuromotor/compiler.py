"""XLA compiler options for the simulation programs, applied per program (never globally).

A step of the 19-joint model is a few hundred small kernels (3x3 blocks, vectors of 18 joints,
one 54 x 54 factorization). Three of XLA:CPU's defaults are tuned for large arrays and cost
time at this size:

* ``xla_cpu_experimental_ynn_fusion_type``: small batched dots (18 x 3 x 9, ...) are handed to
  the YNNPACK library, whose per-call set-up outweighs the arithmetic; XLA's own loops win.
* ``xla_cpu_multi_thread_eigen``: Eigen splits even 19 x 19 products over the thread pool.
* ``xla_cpu_use_fusion_emitters``: the newer fusion emitters generate slower code for these
  tiny fusions (and take longer to compile).

Switching the three off made the rollout 18 to 21 % faster in interleaved timings of the same
program in one process (``docs/benchmarks.md``); results agree with the default build to
3e-14 rad. The options are passed to ``jax.jit(..., compiler_options=...)`` of the rollout
programs only, so other JAX code in the user's process is untouched. They are CPU options:
other backends ignore them. They are read when a program is wrapped (at import for the
module-level ones): set ``NEUROMOTOR_XLA_TUNING=0`` before importing neuromotor to compile
with XLA's defaults.
"""

from __future__ import annotations

import os

import jax

CPU_COMPILER_OPTIONS: dict[str, object] = {
    "xla_cpu_experimental_ynn_fusion_type": "",
    "xla_cpu_multi_thread_eigen": False,
    "xla_cpu_use_fusion_emitters": False,
}


def compiler_options() -> dict[str, object]:
    """The options (empty when ``NEUROMOTOR_XLA_TUNING=0``). Deciding does not touch the JAX
    backend, so wrapping a program at import does not fix the device count early."""
    if os.environ.get("NEUROMOTOR_XLA_TUNING", "1").strip().lower() in ("0", "false", "no", "off"):
        return {}
    return dict(CPU_COMPILER_OPTIONS)


def jit(fun, **kwargs):
    """``jax.jit`` with :func:`compiler_options` (a drop-in for the rollout programs)."""
    return jax.jit(fun, compiler_options=compiler_options() or None, **kwargs)
