"""``[sim] still = T`` (issue 37): the capture's pose at clip time T held with zero velocity
over the whole window; the feedforward holds it against gravity. Unperturbed it stays on that
pose (which is the clip's, by forward kinematics of the file), and a push on it recovers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.config import ConfigError, SimulationConfig, simulation_config
from neuromotor.config.specs import DEFAULT_HIT
from neuromotor.model.clip_edit import forward_kinematics
from neuromotor.model.load import load_character
from neuromotor.rotations import quat_to_matrix
from neuromotor.studies import metrics as mx
from neuromotor.studies.simulate import deviation_curve, prepare, run, simulate_jit, window_steps

FRAME = 150  # the held frame of the MocapBank clip (5 s at 30 Hz: a crouch, hips at half standing height)
PUSH = dict(DEFAULT_HIT, body="chest", magnitude=400.0, start=0.2, direction="forward")


@pytest.fixture(scope="module")
def bank():
    return load_character(CLIPS["mocapbank"])


@pytest.fixture(scope="module")
def still(bank):
    """The still pose, legs held, unperturbed (a run of its own) and pushed (run(): both rollouts)."""
    character, traj = bank
    t = FRAME * character.clip.frame_time
    quiet = prepare(SimulationConfig(still=t, duration=1.5, driven_joints=["legs"]), character, traj)
    pushed = prepare(dataclasses.replace(quiet.config, perturbations=[PUSH]), character, traj)
    return quiet, simulate_jit(quiet.sim_model, quiet.params), pushed, run(pushed)


def _joint_origins(model, states):
    """World joint origins of the bodies' joints: body COM less the rotated COM offset."""
    rot = np.asarray(quat_to_matrix(states.quat))
    return np.asarray(states.pos) - np.einsum("...bij,bj->...bi", rot, np.asarray(model.com))


def test_unperturbed_still_run_holds_the_clips_pose(bank, still):
    character, _ = bank
    quiet, base, _, _ = still
    model = quiet.model
    assert quiet.options.n_steps == 180  # 1.5 s at 120 Hz, from clip time 0 (sim.start)
    # The pose is the file's at that frame: joint origins by forward kinematics of the BVH
    # channels themselves (not the spline), at every step of the run.
    fk, _, _ = forward_kinematics(character.clip, [FRAME])
    want = fk[0][list(model.body_joint)]
    origins = _joint_origins(model, base.states)
    assert np.abs(origins - want).max() < 1e-9
    # ... held: no joint turns from it, no body moves (the root's velocity is exactly zero).
    turn = np.asarray(mx.joint_angle_changes_deg(model, base.states.quat, base.states.quat[:1]))
    assert np.deg2rad(turn.max()) < 1e-6
    assert np.abs(np.asarray(base.theta) - np.asarray(base.theta[0])).max() < 1e-6
    assert np.abs(np.asarray(base.states.vel)).max() < 1e-6 and np.abs(np.asarray(base.states.omega)).max() < 1e-6
    assert not np.any(np.asarray(base.states.vel[:, 0])) and not np.any(np.asarray(base.states.omega[:, 0]))
    assert float(base.residual.max()) < 1e-9 and float(base.violation.max()) < 1e-9
    # Nothing in the window comes from the clip's other frames: the reference is constant.
    assert np.ptp(np.asarray(quiet.ref.theta), axis=0).max() == 0.0
    # The feedforward holds the pose against gravity: the same, non-zero torques every step.
    tau = np.asarray(quiet.ref.tau)
    assert np.abs(tau).max() > 1.0 and np.abs(tau - tau[:1]).max() < 1e-9 * np.abs(tau).max()


def test_unperturbed_still_run_is_runs_unperturbed_rollout(still):
    _, base, _, result = still
    twin = result.unperturbed
    for a, b in ((base.states.pos, twin.states.pos), (base.states.quat, twin.states.quat), (base.theta, twin.theta)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)


def test_a_push_on_a_still_posture_recovers(still):
    _, _, pushed, result = still
    m = result.metrics
    assert not m["diverged"] and m["max_kkt_residual"] < 1e-6
    assert m["unperturbed_rms_error_deg"] < 1e-6  # the twin holds the pose
    t = np.asarray(result.perturbed.time)
    d = deviation_curve(pushed, result.perturbed, result.unperturbed)
    assert d[t <= PUSH["start"]].max() < 1e-9  # the push acts in the window's clock: nothing before it
    assert m["peak_deviation_deg"] > 1.0  # the push moves the body...
    assert np.isfinite(m["recovery_time_s"]) and m["recovery_time_s"] < 1.0  # ...back within 0.5 deg
    # ...and the swaying free limbs settle: the last 0.5 s sway less than half the first 0.5 s.
    after = t - PUSH["start"]
    assert d[after >= 0.8].max() < 0.5 * d[(after >= 0) & (after < 0.5)].max()
    assert d[-10:].max() < 0.25 * m["peak_deviation_deg"]


def test_still_windows_and_their_errors(bank):
    character, traj = bank
    end = character.clip.duration
    # A held pose needs no frames: any duration, by default the clip's, from any start.
    cfg = SimulationConfig(still=end, start=end - 0.5, duration=2.0, source="cfg.toml")
    assert window_steps(cfg, end) == 240
    assert window_steps(dataclasses.replace(cfg, duration=None), end) == round(end * 120)
    with pytest.raises(ConfigError, match="runs past the clip's end"):
        window_steps(dataclasses.replace(cfg, still=None), end)
    for bad in (end + 0.1, 1e9):
        with pytest.raises(ConfigError, match=r"^cfg.toml: field 'sim.still' = .* is outside the clip \(0 to "):
            prepare(dataclasses.replace(cfg, still=bad), character, traj)
    # A perturbation must act in the simulated window, which a still pose keeps in its own clock.
    late = dataclasses.replace(cfg, duration=1.0, perturbations=[dict(PUSH, start=end + 0.6)])
    with pytest.raises(ConfigError, match=r"perturbation\[0\].start.*held still"):
        prepare(late, character, traj)
    # Driven through a keyword: the push on it is refused, naming the entry that drives it.
    belted = dataclasses.replace(cfg, driven_joints=["arms", "trunk", "pelvis"], perturbations=[PUSH])
    with pytest.raises(ConfigError) as e:
        prepare(belted, character, traj)
    assert str(e.value) == (
        "cfg.toml: field 'perturbation[0].body' = 'chest' (body Chest2) is a driven body (by sim.driven_joints "
        "entry 'trunk'): a push on it does nothing"
    )


@pytest.mark.parametrize(
    "value, message",
    [(-0.5, "must be >= 0"), ("noon", "must be a finite number"), (True, "must be a finite number")],
)
def test_still_field_is_checked_when_parsed(value, message):
    with pytest.raises(ConfigError, match=rf"^cfg.toml: field 'sim.still' {message}"):
        simulation_config({"sim": {"still": value}}, "cfg.toml")


def test_a_still_run_file_records_and_exports_the_held_pose(bank, still, tmp_path):
    """RUN.npz records the held clip time and the driven bodies by name (the keyword resolved);
    export-bvh writes the pose of that clip time: the root and the driven legs stay on the
    file's frame while the pushed upper body moves."""
    import json

    from neuromotor.io.export import export_bvh
    from neuromotor.io.runfile import save_npz_atomic
    from neuromotor.model.bvh import read_bvh
    from neuromotor.studies.record import run_arrays

    character, _ = bank
    _, _, pushed, result = still
    arrays = run_arrays(pushed, result)
    t = FRAME * character.clip.frame_time
    assert float(arrays["clip_still"]) == t
    prov = json.loads(str(arrays["provenance_json"]))
    legs = [n for n in character.model.body_names if n.endswith(("Hip", "Knee", "Ankle"))]
    assert prov["still"] == t and prov["driven_joints"] == legs and prov["driven_joints_requested"] == ["legs"]
    save_npz_atomic(tmp_path / "run.npz", arrays)
    out = read_bvh(export_bvh(tmp_path / "run.npz", tmp_path / "run.bvh"), units=1.0)
    source = read_bvh(CLIPS["mocapbank"], units=1.0)
    pos, _, ends = forward_kinematics(out)
    want, _, want_ends = forward_kinematics(source, [FRAME])
    held = [0] + [source.joint_index(n) for n in legs]
    scale = float(np.abs(want[0]).max())
    assert np.abs(pos[:, held] - want[:, held]).max() < 1e-5 * scale
    assert np.abs(ends[:, held] - want_ends[:, held]).max() < 1e-5 * scale
    arm = source.joint_index("LeftWrist")
    assert np.abs(pos[:, arm] - want[:, arm]).max() > 1e-3 * scale  # the push moved the free upper body
