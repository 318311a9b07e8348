"""Fit targets from recordings (studies/targets.py): a recorded trial as BVH on the same
skeleton, and corridors (mean and standard deviation over subjects) weighted by their width."""

import numpy as np
import pytest

from conftest import ALL_CLIPS, CLIPS
from neuromotor.config import ConfigError, SimulationConfig, simulation_config
from neuromotor.config.parse import fit_spec
from neuromotor.studies.fit import trajectory_calibration
from neuromotor.studies.simulate import load_character, prepare
from neuromotor.studies.targets import read_target, write_target_csv

PUSH = dict(kind="force", body="chest", point=[0.0, 0.1, 0.0], direction=[0.0, 0.0, 1.0], magnitude=300.0,
            start=0.55, duration=0.05)


@pytest.fixture(scope="module")
def setup():
    character, traj = load_character(CLIPS["mocapbank"])
    return prepare(SimulationConfig(start=0.5, duration=0.25, perturbations=[PUSH]), character, traj)


def test_recorded_trial_bvh_gives_the_models_joint_angles(setup):
    """The source clip itself read as a 'recorded trial': its channels are the model's mocap
    joint angles theta_d (the reference the controller tracks) at the clip's frames (30 fps:
    every 4th step of the 1/120 s grid; between frames the target interpolates linearly and the
    reference by spline)."""
    table = read_target(CLIPS["mocapbank"])
    dofs = list(setup.model.dof_names)
    problem, target, w, labels = trajectory_calibration(setup, table, "joint_angles", dofs)
    s = problem.spec
    want = np.asarray(setup.ref.theta[s.i0:s.i1])
    got = target.reshape(want.shape)
    assert abs(table.time[1] - 4 * setup.options.h) < 1e-6 and abs(setup.ref.time[0] / table.time[1] - 15) < 1e-3
    np.testing.assert_allclose(got[::4], want[::4], rtol=0, atol=2e-5)  # the file's frame time has 6 digits
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-3)
    assert labels == tuple(dofs) and np.all(w == 1.0)
    # A trial recorded from t = 0.4 s of the clip's clock: the same angles, shifted.
    late = read_target(CLIPS["mocapbank"], time_offset=0.4)
    np.testing.assert_allclose(late.time - table.time, 0.4)


@pytest.mark.parametrize("clip", sorted(ALL_CLIPS))
def test_every_clip_reads_as_a_recorded_trial(clip):
    """Every shipped clip, whatever its channel orders, units and root: a column per non-root
    rotation channel, named like the model's DOFs, continuous in time (unwrapped)."""
    table = read_target(ALL_CLIPS[clip])
    character, _ = load_character(ALL_CLIPS[clip]) if clip == "mocapbank_19joint" else (None, None)
    assert table.values.shape == (1, table.time.size, len(table.names)) and table.radians
    assert np.max(np.abs(np.diff(table.values, axis=1))) < np.pi
    if character is not None:
        assert set(character.model.dof_names) <= set(table.names)


def _corridor_csv(path, setup, sd_deg):
    names = ["Chest.Xrotation", "Chest2.Xrotation"]
    time = np.linspace(0.45, 0.8, 15)
    mean = np.stack([np.sin(3 * time), np.cos(2 * time)], -1)[None] * 10.0
    sd = np.broadcast_to(np.asarray(sd_deg, float), mean.shape)
    cols = [c for n in names for c in (n, n + ".sd")]
    vals = np.stack([a for k in range(2) for a in (mean[..., k], sd[..., k])], -1)
    write_target_csv(path, time, cols, vals)
    return names, time, mean, sd


def test_corridor_weights_each_sample_by_its_width(setup, tmp_path):
    sd_deg = np.stack([np.linspace(1.0, 4.0, 15), np.full(15, 2.0)], -1)[None]
    names, time, mean, sd = _corridor_csv(tmp_path / "corridor.csv", setup, sd_deg)
    table = read_target(tmp_path / "corridor.csv")
    assert table.names == tuple(names) and table.sd is not None
    problem, target, w, _ = trajectory_calibration(setup, table, "joint_angles", names, {"Chest2.Xrotation": 3.0},
                                                   angle_unit="deg")
    s = problem.spec
    grid = np.asarray(setup.ref.time[s.i0:s.i1])
    want_sd = np.deg2rad(np.stack([np.interp(grid, time, sd[0, :, k]) for k in range(2)], -1))
    want_mean = np.deg2rad(np.stack([np.interp(grid, time, mean[0, :, k]) for k in range(2)], -1))
    np.testing.assert_allclose(target.reshape(-1, 2), want_mean, rtol=1e-9)  # the CSV holds 12 digits
    np.testing.assert_allclose(w.reshape(-1, 2), np.array([1.0, 3.0]) / want_sd, rtol=1e-9)


def test_bad_corridors_and_bvh_targets_are_refused(setup, tmp_path):
    _corridor_csv(tmp_path / "zero.csv", setup, [0.0, 1.0])
    with pytest.raises(ConfigError, match=r"zero.csv: field 'Chest.Xrotation.sd' must be finite and > 0"):
        read_target(tmp_path / "zero.csv")
    (tmp_path / "half.csv").write_text("time,A.Xrotation,A.Xrotation.sd,B.Xrotation\n0,1,1,1\n1,1,1,1\n")
    with pytest.raises(ConfigError, match=r"half.csv: field 'B.Xrotation.sd' column is missing"):
        read_target(tmp_path / "half.csv")
    cfg = simulation_config({"perturbation": [PUSH]}, "f.toml")
    target = {"kind": "joint_angles", "file": "trial.bvh", "angle_unit": "deg"}
    with pytest.raises(ConfigError, match=r"f.toml: field 'fit.target.angle_unit' does not apply to a BVH"):
        fit_spec({"fit": {"target": target}}, cfg)
    target = {"kind": "joint_angles", "file": "trial.csv", "time_offset": 0.2}
    with pytest.raises(ConfigError, match=r"f.toml: field 'fit.target.time_offset' applies to a BVH target only"):
        fit_spec({"fit": {"target": target}}, cfg)
    with pytest.raises(ConfigError, match=r"a BVH target gives joint angles"):
        read_target(CLIPS["mocapbank"], "body_positions")
