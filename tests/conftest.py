import os
import pathlib

import jax
import pytest

jax.config.update("jax_enable_x64", True)
# The suite is mostly XLA compilation of programs that then run for a second or less: LLVM's
# backend optimizations cost more compile time than they save here (same results; no timing is
# tested). NEUROMOTOR_TEST_FAST_COMPILE=0 compiles as users do. Subprocesses inherit it.
if os.environ.get("NEUROMOTOR_TEST_FAST_COMPILE", "1") != "0" and "xla_backend_optimization_level" not in \
        os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()
# Persistent compilation cache: rollouts compile once per shape, also across CLI subprocesses.
_CACHE = pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(_CACHE))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED_MOCAP = REPO.parent / "shared" / "mocap"
CLIPS = {
    "mocapbank": SHARED_MOCAP / "mocapbank_19joint.bvh",
    "walk": SHARED_MOCAP / "walk_22joint_zyx.bvh",
}
# Every shipped clip (CMU jumps, Bandai-Namco kick with a ground-marker root, ...).
ALL_CLIPS = {p.stem: p for p in sorted(SHARED_MOCAP.glob("*.bvh"))}
SHARED = SHARED_MOCAP if SHARED_MOCAP.exists() else None


@pytest.fixture(scope="session", params=sorted(CLIPS))
def clip_path(request):
    path = CLIPS[request.param]
    if not path.exists():
        pytest.fail(f"shared mocap clip missing: {path} (CI must have ../shared beside the repo)")
    return path
