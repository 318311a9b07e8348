"""Issue 17: a sweep run as two processes with jax.distributed (CPU collectives on 127.0.0.1)
gives the one-process table, only process 0 writes, and bad options are refused.

The cost is the two child interpreters tracing and compiling the sweep of a 4-body clip (one
XLA thread each, so the pair fits the CI machine's two cores); the one-process reference is
computed in this process meanwhile.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from neuromotor import distributed
from neuromotor.studies import sweep as sw
from test_sweep import tiny_bvh

CHILD_TIMEOUT_S = 240


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    d = tmp_path_factory.mktemp("dist")
    tiny_bvh(d / "tiny.bvh")
    cfg = d / "sweep.toml"
    # 9 runs: shares of 4 and 5; the middle gain setting's runs fall in both shares; 1e6 N diverges.
    cfg.write_text(textwrap.dedent("""\
        clip = "tiny.bvh"
        [sim]
        duration = 0.6
        [[perturbation]]
        body = "Forearm"
        point = [0.1, 0.0, 0.0]
        direction = [0.0, 0.0, 1.0]
        magnitude = 20.0
        start = 0.2
        [sweep]
        magnitudes = [15.0, 1e6, 30.0]
        ks = [400.0, 150.0, 60.0]
        kd = [20.0]
        chunk = 2
        """))
    return cfg


def _start_ranks(cfg, outs):
    """Rank i of 2 writing (if it writes) into outs[i]; explicit --coordinator options, as on a cluster."""
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + " ".join(distributed.SINGLE_THREAD_FLAGS)).strip())
    coordinator = f"127.0.0.1:{distributed.free_port()}"
    return [subprocess.Popen([sys.executable, "-m", "neuromotor", "sweep", str(cfg), "-o", str(out), "--no-progress",
                              "--coordinator", coordinator, "--num-processes", "2", "--process-id", str(i),
                              "--process-timeout", "120"],
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for i, out in enumerate(outs)]


def _wait(children) -> list[tuple[int, str, str]]:
    try:
        return [(c.returncode, *c.communicate(timeout=CHILD_TIMEOUT_S)) for c in children]
    except subprocess.TimeoutExpired:
        for c in children:
            c.kill()
        pytest.fail(f"the two-process sweep did not finish within {CHILD_TIMEOUT_S} s")


@pytest.fixture(scope="module")
def two_and_one(config, tmp_path_factory):
    d = tmp_path_factory.mktemp("outs")
    outs = [d / "rank0", d / "rank1"]
    children = _start_ranks(config, outs)
    one, _ = sw.sweep_from_config(config, d / "one", progress=False)  # the reference, meanwhile
    done = _wait(children)
    for i, c in enumerate(children):
        assert c.returncode == 0, f"rank {i}: {done[i][2][-3000:]}"
    return outs, done, one


def test_two_process_table_equals_one_process_table(two_and_one):
    outs, done, one = two_and_one
    rows = sw.read_csv(outs[0] / "sweep.csv")
    assert [r["run"] for r in rows] == list(range(9))  # grid order
    assert sum(r["diverged"] for r in rows) == 3  # the 1e6 N hits, in both shares
    for a, b in zip(one.rows, rows):
        for k in sw.COLUMNS:
            x, y = a[k], b[k]
            if isinstance(x, float) and math.isnan(x):
                assert math.isnan(y), (a["run"], k)
            elif isinstance(x, (float, int)) and not isinstance(x, bool):
                assert abs(x - y) <= 1e-12, (a["run"], k, x, y)
            else:
                assert x == y, (a["run"], k)
    assert "9 runs (3 diverged)" in done[0][1]


def test_only_rank_zero_writes(two_and_one):
    outs, done, _ = two_and_one
    assert sorted(p.name for p in outs[0].iterdir()) == ["sweep.csv", "sweep.png"]  # no temporaries left
    assert not outs[1].exists() or not any(outs[1].iterdir())
    assert "wrote" not in done[1][1]  # rank 1 reports nothing either (stdout holds gloo's connection line)


@pytest.mark.parametrize("options", [
    ["--num-processes", "0"],
    ["--process-id", "-1"],
    ["--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "2"],
    ["--coordinator", "nohost", "--num-processes", "2", "--process-id", "0"],
    ["--coordinator", "127.0.0.1:1"],
    ["--local-processes", "2", "--process-id", "0"],
    ["--local-processes", "0"],
    ["--process-timeout", "0"],
])
def test_bad_process_options_exit_2_with_one_line(config, tmp_path, capsys, options):
    from neuromotor.cli import main

    try:
        status = main(["sweep", str(config), "-o", str(tmp_path / "o"), *options])
    except SystemExit as e:  # refused by the argument parser
        status = e.code
    assert status == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuromotor sweep: error:") and "\n" not in err, err
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_shares_are_contiguous_and_balanced():
    for n in (1, 2, 7, 9, 64):
        for count in (1, 2, 3, 8):
            bounds = [distributed.share(n, r, count) for r in range(count)]
            assert bounds[0][0] == 0 and bounds[-1][1] == n
            assert all(a[1] == b[0] for a, b in zip(bounds, bounds[1:]))
            sizes = [hi - lo for lo, hi in bounds]
            assert max(sizes) - min(sizes) <= 1


CHILD = "import os, sys, time; " \
        "i = int(sys.argv[sys.argv.index('--process-id') + 1]); " \
        "open(os.path.join(sys.argv[1], f'rank{i}'), 'w').write(' '.join(sys.argv[2:]) + '|' + os.environ['XLA_FLAGS']); " \
        "time.sleep(float(sys.argv[2 + i]) if i == 0 else 0); sys.exit(int(sys.argv[4]) if i == 1 else 0)"


def test_local_launch_ranks_and_failure_stops_the_others(tmp_path):
    """launch_local (``--local-processes``): ranks 0..N-1 on one coordinator, one XLA thread
    each; a rank that fails ends the launch at once, with its status, and stops the rest."""
    prog = [sys.executable, "-c", CHILD, str(tmp_path)]
    assert distributed.launch_local(["0", "0", "0"], 2, program=prog) == 0
    seen = [(tmp_path / f"rank{i}").read_text() for i in range(2)]
    coords = {s.split("--coordinator ")[1].split()[0] for s in seen}
    assert len(coords) == 1 and next(iter(coords)).startswith("127.0.0.1:")
    assert all("--num-processes 2" in s and "intra_op_parallelism_threads=1" in s for s in seen)
    import time

    t = time.monotonic()
    assert distributed.launch_local(["60", "0", "3"], 2, program=prog) == 3  # rank 0 would sleep 60 s
    assert time.monotonic() - t < 30
