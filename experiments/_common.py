"""Shared start-up for the experiment scripts: float64 and the persistent compile cache."""

import os
import pathlib

REPO = pathlib.Path(__file__).resolve().parents[1]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(REPO / ".jax_cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


def add_distributed_args(ap) -> None:
    """Multi-process flags shared by the sweep scripts (neuromotor.distributed; README: sweeps
    across processes and hosts)."""
    from neuromotor.distributed import add_arguments

    add_arguments(ap)


def init_distributed(args) -> None:
    """Join the multi-process job the flags describe; with ``--local-processes N``, run this
    script as N local processes instead and exit with their status."""
    import sys

    from neuromotor import distributed
    from neuromotor.errors import UserError

    try:
        procs = distributed.from_args(args)
        if (args.local_processes or 1) > 1:
            argv = distributed.without_option(sys.argv[1:], "--local-processes")
            sys.exit(distributed.launch_local(argv, args.local_processes, args.process_timeout,
                                              program=[sys.executable, sys.argv[0]]))
        if procs is not None:
            distributed.initialize(procs)
    except UserError as e:
        print(f"{pathlib.Path(sys.argv[0]).stem}: error: {e}", file=sys.stderr)
        sys.exit(2)
