"""XLA compiler options for the simulation programs, applied per program (never globally).

A step of the 19-joint model is a few hundred small kernels (3x3 blocks, vectors of 18 joints,
one 54 x 54 factorization). Three of XLA:CPU's defaults are tuned for large arrays and cost
time at this size:

* ``xla_cpu_experimental_ynn_fusion_type``: small batched dots (18 x 3 x 9, ...) are handed to
  the YNNPACK library, whose per-call set-up outweighs the arithmetic; XLA's own loops win.
* ``xla_cpu_multi_thread_eigen``: Eigen splits even 19 x 19 products over the thread pool.
* ``xla_cpu_use_fusion_emitters``: the newer fusion emitters generate slower code for these
  tiny fusions (and take longer to compile).

Switching the three off makes the rollout faster with the same results to round-off (figures and
commands: ``docs/benchmarks.md``, "Compiler options"), and compiles faster too: without the
fusion emitters the reference grid of a run (inverse dynamics included) compiles in about half
the time. Every program of the package is built by :func:`jit`, which passes the options to
``jax.jit(..., compiler_options=...)`` of that program only, so other JAX code in the user's
process is untouched. They are given only when the default backend is the CPU, decided at a program's first
use (wrapping a program at import touches no backend, so a device count forced later still takes
effect). Set ``NEUROMOTOR_XLA_TUNING=0`` to compile with XLA's defaults.

A float32 compile with these options was reported to exhaust memory on one rig (issue 35); it did
not reproduce, so they stay: ``tests/physics/test_compile_memory.py`` guards the peak of a cold
float32 ``simulate`` (docs/benchmarks.md, "Compile memory").
"""

from __future__ import annotations

import functools
import os
import pathlib

import jax

CPU_COMPILER_OPTIONS: dict[str, str | bool] = {
    "xla_cpu_experimental_ynn_fusion_type": "",
    "xla_cpu_multi_thread_eigen": False,
    "xla_cpu_use_fusion_emitters": False,
}


def compiler_options() -> dict[str, str | bool]:
    """The options (empty when ``NEUROMOTOR_XLA_TUNING=0``). Deciding does not touch the JAX
    backend, so wrapping a program at import does not fix the device count early."""
    if os.environ.get("NEUROMOTOR_XLA_TUNING", "1").strip().lower() in ("0", "false", "no", "off"):
        return {}
    return dict(CPU_COMPILER_OPTIONS)


class _TunedJit:
    """``jax.jit(fun, **kwargs)`` built at first use, with the options if the backend is the CPU."""

    def __init__(self, fun, kwargs):
        self._fun, self._kwargs, self._jitted, self._nested = fun, kwargs, None, None
        functools.update_wrapper(self, fun)

    def _get(self):
        if self._jitted is None:
            opts = compiler_options() if jax.default_backend() == "cpu" else {}
            self._jitted = jax.jit(self._fun, compiler_options=opts or None, **self._kwargs)
        return self._jitted

    def __call__(self, *args, **kwargs):
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs))):
            # Called inside another program, which is compiled with its own options (JAX takes
            # compiler options on top-level programs only).
            if self._nested is None:
                self._nested = jax.jit(self._fun, **self._kwargs)
            return self._nested(*args, **kwargs)
        return self._get()(*args, **kwargs)

    def lower(self, *args, **kwargs):
        return self._get().lower(*args, **kwargs)


def jit(fun, **kwargs):
    """``jax.jit`` with :func:`compiler_options` on the CPU (a drop-in for the package's programs:
    call it, or ``.lower(...).compile()`` it)."""
    return _TunedJit(fun, kwargs)


# --- Persistent compilation cache (the CLI turns it on; importing the package does not) ---

_OFF = ("off", "0", "none", "false", "no", "")


def cache_dir() -> pathlib.Path | None:
    """Folder of the persistent compilation cache for the CLI, or None when disabled.

    ``NEUROMOTOR_CACHE_DIR`` (``off`` disables), else ``$XDG_CACHE_HOME/neuromotor/jax``, else
    ``~/.cache/neuromotor/jax``. (A cache folder already given to JAX, by
    ``JAX_COMPILATION_CACHE_DIR`` or ``jax.config``, is left as it is: see
    :func:`enable_compile_cache`.)"""
    env = os.environ.get("NEUROMOTOR_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in _OFF else pathlib.Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "neuromotor" / "jax"


def enable_compile_cache(min_compile_time_s: float = 0.0) -> str | None:
    """Turn on JAX's persistent compilation cache so that a second ``neuromotor simulate`` loads
    its programs instead of compiling them again (JAX keys entries by program, backend, compiler
    options and versions, and writes them atomically, so concurrent runs share it safely).

    Returns the folder in use, or None. ``NEUROMOTOR_CACHE_DIR=off`` disables it; an already set
    ``JAX_COMPILATION_CACHE_DIR`` (or ``jax_compilation_cache_dir``) is respected. A folder that
    cannot be created leaves the cache off (compiling as before) rather than failing. Every
    program is cached (``min_compile_time_s`` 0): the hundred small ones of a run add up to a
    few seconds (measured: second ``simulate`` 12.6 s with a 0.5 s threshold, 9.4 s with 0).
    What remains of a warm start is Python tracing, which no cache skips."""
    env = os.environ.get("NEUROMOTOR_CACHE_DIR")
    if env is not None and env.strip().lower() in _OFF:
        return None
    current = jax.config.jax_compilation_cache_dir or os.environ.get("JAX_COMPILATION_CACHE_DIR")  # type: ignore[attr-defined]
    if current:
        if not jax.config.jax_compilation_cache_dir:  # type: ignore[attr-defined]  # a JAX flag
            jax.config.update("jax_compilation_cache_dir", current)
        return str(current)
    path = cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    return str(path)


# --- One CPU device per core (the CLI asks for it; importing the package does not) ---

_LEAVE = ("xla_force_host_platform_device_count", "intra_op_parallelism_threads")


def cpu_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def one_runtime_thread() -> bool:
    """Ask XLA:CPU's runtime for one intra-op thread (``PJRT_NPROC=1``) before JAX starts.

    With more, XLA:CPU hands groups of a program's ready kernels to its thread pool and waits
    for them: the contact step paid about six thread hand-offs a step, 1.3-2x its time on a
    quiet 2-core host and 5-20x when the other core is busy (docs/benchmarks.md, "Thread
    hand-offs"). Kernels are this project's small ones, so nothing runs faster on the pool;
    devices (batches split over cores) keep their own threads. The CLI asks for it only for a
    free-root run (``simulate``, ``fit``, ``bench --free-only``): a driven-root run gained
    nothing, and XLA compiled up to 10% slower with one thread. Left alone, returning False, when
    ``PJRT_NPROC`` or ``NPROC`` is set or JAX's backends already run."""
    from jax._src import xla_bridge

    if "PJRT_NPROC" in os.environ or "NPROC" in os.environ or xla_bridge.backends_are_initialized():
        return False
    os.environ["PJRT_NPROC"] = "1"
    return True


def use_cpu_cores(split: bool = True) -> int | None:
    """Give JAX one CPU device per core, so that a batch split over the devices runs one share
    per core (:func:`neuromotor.studies.sweep.runner.shard_vmap`). On one device XLA:CPU runs
    a batch's small kernels one after another and splits only the large ones over the cores: a
    batch of 256 rollouts ran 1.3x as fast split over two devices on a 2-core machine
    (docs/benchmarks.md, "Issue 17: one device per core").

    ``split`` False (a command of single trajectories: ``simulate``, ``fit``, ...): one device
    unless a count is given. A second device gains a single trajectory nothing and costs a
    floating root's contact step thread hand-offs (docs/benchmarks.md, "Thread hand-offs").

    ``NEUROMOTOR_CPU_DEVICES``: ``auto`` (default: the core count, or 1 when not ``split``), a
    count, or ``1``/``off`` for one device. Left alone, returning None, once JAX's backends are running (the count is
    fixed at start-up), or when the device count or XLA:CPU's threads were already chosen:
    ``JAX_NUM_CPU_DEVICES``, ``jax_num_cpu_devices``, or ``XLA_FLAGS`` forcing the host device
    count or the intra-op threads (the processes of a distributed sweep run one thread each).
    Returns the count set otherwise."""
    from jax._src import xla_bridge

    env = os.environ.get("NEUROMOTOR_CPU_DEVICES", "auto").strip().lower()
    if env in _OFF or env == "1":
        return None
    if env == "auto":
        count = cpu_cores() if split else 1
    elif env.isdigit():
        count = int(env)
    else:
        from neuromotor.errors import UserError

        raise UserError(f"NEUROMOTOR_CPU_DEVICES: expected 'auto', 'off' or a device count, got {env!r}")
    flags = os.environ.get("XLA_FLAGS", "")
    chosen = (
        "JAX_NUM_CPU_DEVICES" in os.environ
        or jax.config.jax_num_cpu_devices > 0  # type: ignore[attr-defined]
        or any(name in flags for name in _LEAVE)
    )
    if count < 2 or chosen or xla_bridge.backends_are_initialized():
        return None
    jax.config.update("jax_num_cpu_devices", count)
    return count
