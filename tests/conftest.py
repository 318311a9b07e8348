import pathlib

import jax
import pytest

jax.config.update("jax_enable_x64", True)

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED_MOCAP = REPO.parent / "shared" / "mocap"
CLIPS = {
    "mocapbank": SHARED_MOCAP / "mocapbank_19joint.bvh",
    "walk": SHARED_MOCAP / "walk_22joint_zyx.bvh",
}


@pytest.fixture(scope="session", params=sorted(CLIPS))
def clip_path(request):
    path = CLIPS[request.param]
    if not path.exists():
        pytest.fail(f"shared mocap clip missing: {path} (CI must have ../shared beside the repo)")
    return path
