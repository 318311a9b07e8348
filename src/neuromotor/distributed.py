"""Sweeps across processes and hosts on JAX's multi-controller runtime (``jax.distributed``).

N processes run the same command on the same config: one per host, one per GPU, or several
on one machine (CPU collectives over gloo). Each builds the whole grid, simulates its
contiguous share of the runs on its own devices (:func:`share`), and the per-run arrays of all
shares are gathered with :func:`jax.experimental.multihost_utils.process_allgather`
(:func:`gather_shares`), so that every process holds the table in grid order and process 0
writes it. Nothing but the final gather crosses processes: processes never wait on each other
chunk by chunk, and hosts with different devices may run at their own pace.

Start-up (:func:`initialize`) must come before any JAX computation; the coordinator address,
process count and id come from explicit arguments or, on SLURM, Open MPI and the other
clusters JAX detects, from the environment. A process that fails or hangs does not block the
others forever: they wait at most ``timeout_s`` for it at the gather (a barrier of JAX's
coordination service), and JAX's runtime ends every process of the job when one of them dies
(heartbeat) or leaves early (shutdown barrier), after at most ``timeout_s`` as well.
:func:`launch_local` starts N processes on 127.0.0.1 and stops the rest as soon as one fails.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import socket
import subprocess
import sys
import time
from collections.abc import Sequence

import jax
import numpy as np

from neuromotor.errors import UserError

# One XLA:CPU thread per local process: N processes on N cores, not N x cores threads.
SINGLE_THREAD_FLAGS = ("--xla_cpu_multi_thread_eigen=false", "intra_op_parallelism_threads=1")
_timeout_s = [600.0]  # the wait for the other processes, from the last initialize()
_gathers = [0]  # gathers so far: every process gathers in the same order, so barrier ids agree


@dataclasses.dataclass(frozen=True)
class Processes:
    """How this process joins a multi-process run. ``coordinator`` (``HOST:PORT`` of process 0),
    ``num_processes`` and ``process_id`` left as None are detected from the environment
    (SLURM, Open MPI, ... as ``jax.distributed.initialize`` does); ``timeout_s`` bounds every
    wait on the other processes (start-up, gather, shutdown)."""

    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    timeout_s: float = 600.0

    def __post_init__(self):
        where = "--coordinator"
        if self.coordinator is not None:
            host, _, port = self.coordinator.rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise UserError(f"{where}: expected HOST:PORT with a port in 1..65535, got {self.coordinator!r}")
        if self.num_processes is not None and self.num_processes < 1:
            raise UserError(f"--num-processes: must be a positive integer, got {self.num_processes}")
        if self.process_id is not None and self.process_id < 0:
            raise UserError(f"--process-id: must be >= 0, got {self.process_id}")
        if None not in (self.num_processes, self.process_id) and self.process_id >= self.num_processes:
            raise UserError(
                f"--process-id: must be below --num-processes ({self.num_processes}), got {self.process_id}"
            )
        if not self.timeout_s > 0:
            raise UserError(f"--process-timeout: must be > 0 s, got {self.timeout_s}")


def _int_from(low: int):
    """An argparse type: an integer >= ``low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {text!r}")
        return value

    return parse


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The multi-process options of ``neuromotor sweep`` and the sweep scripts."""
    g = parser.add_argument_group("several processes (jax.distributed; README: sweeps across processes and hosts)")
    g.add_argument(
        "--local-processes",
        type=_int_from(1),
        metavar="N",
        help="start N processes on this machine (127.0.0.1, one XLA thread each) and wait for them",
    )
    g.add_argument(
        "--coordinator", metavar="HOST:PORT", help="address of process 0 (with --num-processes, --process-id)"
    )
    g.add_argument("--num-processes", type=_int_from(1), metavar="N", help="processes in the job")
    g.add_argument("--process-id", type=_int_from(0), metavar="I", help="this process's rank, 0..N-1")
    g.add_argument(
        "--distributed",
        action="store_true",
        help="join a multi-process job; what is not given is detected (SLURM, Open MPI, ...)",
    )
    g.add_argument(
        "--process-timeout",
        type=_seconds,
        default=600.0,
        metavar="S",
        help="seconds to wait for the other processes at start-up and at the gather (default 600)",
    )


def from_args(args) -> Processes | None:
    """The :class:`Processes` of parsed :func:`add_arguments` options; None for one process
    (also for ``--local-processes``, whose children get explicit options)."""
    explicit = {
        "--coordinator": args.coordinator,
        "--num-processes": args.num_processes,
        "--process-id": args.process_id,
    }
    given = [k for k, v in explicit.items() if v is not None]
    if args.local_processes is not None and (given or args.distributed):
        raise UserError(f"--local-processes starts its own processes: drop {(given or ['--distributed'])[0]}")
    if given and len(given) < 3 and not args.distributed:
        missing = ", ".join(k for k in explicit if k not in given)
        raise UserError(f"{given[0]} needs {missing} too (or --distributed to detect them from SLURM, Open MPI, ...)")
    if not (given or args.distributed):
        return None
    return Processes(args.coordinator, args.num_processes, args.process_id, args.process_timeout)


def initialize(procs: Processes) -> None:
    """``jax.distributed.initialize`` for ``procs`` (CPU collectives: gloo). Must run before any
    JAX computation; calling it again in the same process does nothing."""
    if jax.distributed.is_initialized():
        return
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    t = max(1, int(round(procs.timeout_s)))
    _timeout_s[0] = procs.timeout_s
    try:
        jax.distributed.initialize(
            procs.coordinator,
            procs.num_processes,
            procs.process_id,
            initialization_timeout=t,
            heartbeat_timeout_seconds=min(t, 100),
            shutdown_timeout_seconds=t,
        )
    except (ValueError, TypeError, RuntimeError) as e:  # nothing detected, backend already started, ...
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        guessed = None in (procs.coordinator, procs.num_processes, procs.process_id)
        hint = " (no cluster detected: give --coordinator, --num-processes and --process-id)" if guessed else ""
        raise UserError(f"jax.distributed.initialize: {first}{hint}") from None


def is_lead() -> bool:
    """Process 0: the one that writes outputs and shows progress."""
    return jax.process_index() == 0


def share(n: int, rank: int | None = None, count: int | None = None) -> tuple[int, int]:
    """Runs ``lo:hi`` of ``n`` for process ``rank`` of ``count`` (default: this one): contiguous
    shares in rank order whose sizes differ by at most one."""
    rank = jax.process_index() if rank is None else rank
    count = jax.process_count() if count is None else count
    return rank * n // count, (rank + 1) * n // count


def _wait_for_everyone(timeout_s: float) -> None:
    from jax._src import distributed

    client = distributed.global_state.client
    if client is None:
        return
    try:
        _gathers[0] += 1
        client.wait_at_barrier(f"neuromotor-gather-{_gathers[0]}", int(timeout_s * 1000))
    except Exception as e:  # the runtime's status error: a process failed, or is too slow
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise UserError(
            f"sweep: process {jax.process_index()} waited {timeout_s:g} s for the other processes "
            f"to finish their shares ({first})"
        ) from None


def gather_shares(local: dict[str, np.ndarray], n: int, timeout_s: float | None = None) -> dict[str, np.ndarray]:
    """The per-run arrays of every process's :func:`share` (leading axis: its runs; an empty
    share sends one row, dropped), joined in grid order on every process; ``timeout_s`` (default:
    the one given to :func:`initialize`) bounds the wait. One process: ``local`` itself."""
    count = jax.process_count()
    if count == 1:
        return local
    bounds = [share(n, r, count) for r in range(count)]
    width = max(hi - lo for lo, hi in bounds)
    # process_allgather needs equal shapes: pad each share to the largest by repeating a row.
    pad = {k: np.asarray(v)[np.minimum(np.arange(width), len(v) - 1)] for k, v in local.items()}
    _wait_for_everyone(_timeout_s[0] if timeout_s is None else timeout_s)
    from jax.experimental import multihost_utils

    stacked = multihost_utils.process_allgather(pad, tiled=False)  # (count, width, ...)
    return {k: np.concatenate([v[r, : hi - lo] for r, (lo, hi) in enumerate(bounds)]) for k, v in stacked.items()}


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on right now (for the coordinator of a local run)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def without_option(argv: Sequence[str], name: str) -> list[str]:
    """``argv`` without ``name VALUE`` / ``name=VALUE``."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == name:
            skip = True
        elif not a.startswith(name + "="):
            out.append(a)
    return out


def _single_thread_env() -> dict[str, str]:
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "").split()
    names = {f.split("=")[0] for f in flags}
    env["XLA_FLAGS"] = " ".join(flags + [f for f in SINGLE_THREAD_FLAGS if f.split("=")[0] not in names])
    return env


def _stop(children: list[subprocess.Popen], grace_s: float = 5.0) -> None:
    for c in children:
        if c.poll() is None:
            c.terminate()
    end = time.monotonic() + grace_s
    for c in children:
        try:
            c.wait(max(0.0, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            c.kill()
            c.wait()


def launch_local(argv: Sequence[str], n: int, timeout_s: float = 600.0, program: Sequence[str] | None = None) -> int:
    """Run ``program *argv`` (default: ``python -m neuromotor``) as ``n`` processes on 127.0.0.1
    (one XLA thread each, ranks given by ``--coordinator``, ``--num-processes``,
    ``--process-id``) and wait. The first to fail stops the others; its exit status is returned
    (0: all succeeded)."""
    coordinator = f"127.0.0.1:{free_port()}"
    env = _single_thread_env()
    program = [sys.executable, "-m", "neuromotor"] if program is None else list(program)
    cmd = [
        *program,
        *argv,
        "--coordinator",
        coordinator,
        "--num-processes",
        str(n),
        "--process-timeout",
        f"{timeout_s:g}",
    ]
    children = [subprocess.Popen([*cmd, "--process-id", str(i)], env=env) for i in range(n)]
    try:
        while True:
            codes = [c.poll() for c in children]
            failed = [(i, rc) for i, rc in enumerate(codes) if rc not in (None, 0)]
            if failed:
                i, rc = failed[0]
                print(f"neuromotor: process {i} of {n} exited with status {rc}; stopping the others", file=sys.stderr)
                return rc if rc > 0 else 1
            if all(rc == 0 for rc in codes):
                return 0
            time.sleep(0.05)
    finally:
        _stop(children)
