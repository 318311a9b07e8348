"""Size of the compiled rollout of the working tree and of an earlier commit: HLO instructions,
fusions, LAPACK custom calls and while loops (a restructuring that leaves these alone leaves the
program alone).

    .venv/bin/python experiments/hlo_size.py REV
"""

import collections
import importlib
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_commits as bc  # noqa: E402


def _size(pkg: str) -> str:
    bench = bc._module(pkg, "studies.bench", "bench")
    dy = bc._module(pkg, "physics.dynamics", "dynamics")
    compiler = importlib.import_module(f"{pkg}.compiler")
    s = bench._setup(None, 1.0, "nullspace")
    f = lambda g, ref: dy.rollout(s.model, g, s.pulses, ref, s.options).theta
    txt = compiler.jit(f).lower(s.gains, s.ref).compile().as_text()
    ops = collections.Counter(re.findall(r"= \S+ (\w[\w-]*)\(", txt))
    return (f"{sum(ops.values())} instructions, {txt.count(' fusion(')} fusions, "
            f"{txt.count('custom-call(')} custom calls, {txt.count(' while(')} while loops")


def main(rev: str) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        old = bc._extract(rev, Path(tmp))
        print(f"working tree: {_size('neuromotor')}")
        print(f"{rev}: {_size(old)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1]))
