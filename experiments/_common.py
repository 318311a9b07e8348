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
    """Multi-host flags shared by the sweep scripts (experiments/README.md)."""
    ap.add_argument("--distributed", action="store_true",
                    help="jax.distributed.initialize() first: one process per host (experiments/README.md)")
    ap.add_argument("--coordinator", help="HOST:PORT of process 0 (default: detected from SLURM/MPI/K8s)")
    ap.add_argument("--num-processes", type=int)
    ap.add_argument("--process-id", type=int)


def init_distributed(args) -> None:
    if args.distributed:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
