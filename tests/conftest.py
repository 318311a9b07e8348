import os
import pathlib

import jax
import pytest

jax.config.update("jax_enable_x64", True)
# The suite is mostly XLA compilation of programs that then run for a second or less: LLVM's
# backend optimizations cost more compile time than they save here, and XLA:CPU's newer fusion
# emitters compile these small fusions 1.5x slower (the rollouts already turn them off,
# neuromotor.compiler; same results; no timing is tested). NEUROMOTOR_TEST_FAST_COMPILE=0
# compiles as users do. Subprocesses inherit the flags.
FAST_COMPILE_FLAGS = {"xla_backend_optimization_level": "0", "xla_cpu_use_fusion_emitters": "false"}
if os.environ.get("NEUROMOTOR_TEST_FAST_COMPILE", "1") != "0":
    _flags = os.environ.get("XLA_FLAGS", "")
    _extra = [f"--{k}={v}" for k, v in FAST_COMPILE_FLAGS.items() if k not in _flags]
    os.environ["XLA_FLAGS"] = " ".join([_flags, *_extra]).strip()
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


# Repeats of a default check on the second default clip whose feature the default run covers
# elsewhere: the walk clip's inverse dynamics (and the kinematics under it) by
# test_eq3_residual_every_frame[walk], the idyn command by its mocapbank case. About 80 s of
# compiles; NEUROMOTOR_EXTENDED=1 runs them.
EXTENDED_REPEATS = {
    "tests/physics/test_inverse_dynamics.py::test_cli_idyn_writes_contract_and_fails_cleanly[walk]",
    "tests/physics/test_inverse_dynamics.py::test_eq1_holds_with_mocap_accelerations[walk]",
    "tests/model/test_kinematics.py::test_batched_kinematics_equal_joint_by_joint_recursion[walk]",
}


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid in EXTENDED_REPEATS:
            item.add_marker(pytest.mark.extended)
