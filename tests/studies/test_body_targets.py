"""Issue 37: fit targets on a body's turn about an axis and a body point's displacement along one
(``body_angle``, ``body_position``), relative to the world or to another body, as the change
since the case's onset; several targets and one file per case (subject) in one fit; leave-one-out.

The observables are checked against closed forms and finite differences without a simulation;
the fit tests share one compiled evaluation: two force pushes on the MocapBank clip, 0.5 s at
h = 1/60 s, head pitch (world, about the character's left) and head-relative-to-chest
displacement (along its forward), both as corridors.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.config import ConfigError, simulation_config
from neuromotor.config.parse import fit_spec
from neuromotor.rotations import quat_exp, quat_mul, quat_rotate
from neuromotor.studies import fit as F
from neuromotor.studies.fit.observables import body_angle, body_displacement, identity_quats
from neuromotor.studies.simulate import load_character
from neuromotor.studies.targets import read_series, write_series_csv

# ---------------------------------------------------------------------------------------------
# The observables in closed form

T, K0 = 40, 7
TIME = jnp.linspace(0.0, 1.0, T)


def unit(v):
    v = jnp.asarray(v, jnp.float64)
    return v / jnp.linalg.norm(v)


def rot(axis, angle):
    """Quaternions of the rotations by ``angle`` (T,) about the unit ``axis``."""
    return quat_exp(jnp.asarray(angle)[..., None] * axis)


AXIS = unit([0.3, -0.2, 0.93])
PERP = unit(jnp.cross(AXIS, jnp.array([1.0, 0.0, 0.0])))  # perpendicular to AXIS
THETA = 0.9 * jnp.sin(3.0 * TIME) + 0.4 * TIME  # the turn about the axis (rad)
PHI = 0.7 * (1.0 - jnp.cos(2.0 * TIME))  # a swing about a perpendicular axis, as large
Q0 = unit([0.4, 0.1, -0.7, 0.5])  # an arbitrary starting orientation
COMMON = quat_exp(TIME[:, None] * jnp.array([1.1, -0.6, 0.8]))  # a rotation of the whole chain


def turning_body(axis, perp, base=Q0):
    """R(t) = Rot(perp, phi) Rot(axis, theta) R0, both angles measured from sample K0."""
    return quat_mul(quat_mul(rot(perp, PHI - PHI[K0]), rot(axis, THETA - THETA[K0])), base)


def test_body_angle_is_the_turn_about_the_axis_and_leaves_out_the_swing():
    ident = identity_quats(T)
    got = body_angle(turning_body(AXIS, PERP), ident, K0, AXIS)
    np.testing.assert_allclose(got, THETA - THETA[K0], atol=1e-12)  # swings of up to 80 deg do not count
    # Sign by the right-hand rule: +0.2 rad about +x ("left" when forward is +z, up +y) takes the
    # body's up axis (+y) towards +z (forward): a forward pitch is positive about "left".
    pitched = rot(jnp.array([1.0, 0.0, 0.0]), 0.2 * TIME / TIME[-1])
    angle = body_angle(pitched, ident, 0, jnp.array([1.0, 0.0, 0.0]))
    assert abs(float(angle[-1]) - 0.2) < 1e-12 and float(quat_rotate(pitched[-1], jnp.array([0.0, 1.0, 0.0]))[2]) > 0
    assert abs(float(body_angle(pitched, ident, 0, jnp.array([-1.0, 0.0, 0.0]))[-1]) + 0.2) < 1e-12  # about "right"


def test_relative_to_another_body_cancels_their_common_rotation():
    """O turns arbitrarily (COMMON); B turns with it and, relative to O, about an axis fixed in
    O's frame: the angle relative to O is that turn alone, the axis given in the world at onset."""
    q_other = quat_mul(COMMON, jnp.broadcast_to(unit([0.9, 0.1, 0.3, -0.2]), (T, 4)))
    q_rel = turning_body(AXIS, PERP, unit([0.2, -0.5, 0.3, 0.6]))  # axes in O's frame
    q_body = quat_mul(q_other, q_rel)
    axis_world = quat_rotate(q_other[K0], AXIS)
    np.testing.assert_allclose(body_angle(q_body, q_other, K0, axis_world), THETA - THETA[K0], atol=1e-12)
    # Against the world the same body turns by much more than that (the common rotation counts).
    assert np.abs(body_angle(q_body, identity_quats(T), K0, axis_world) - (THETA - THETA[K0])).max() > 0.3


def test_body_displacement_is_the_motion_along_the_axis_since_onset():
    d = 0.05 * jnp.sin(4.0 * TIME) + 0.02 * TIME  # along the axis (m)
    e = 0.08 * TIME**2  # across it
    lever = jnp.array([0.01, 0.12, -0.03])  # the point, from the body's COM (body frame)
    q_body = turning_body(AXIS, PERP)
    # World: the point moves by d along the axis and e across it while the body turns.
    point = jnp.array([0.2, 1.5, -0.4]) + d[:, None] * AXIS + e[:, None] * PERP
    pos = point - quat_rotate(q_body, jnp.broadcast_to(lever, (T, 3)))
    got = body_displacement(pos, q_body, lever, jnp.zeros((T, 3)), identity_quats(T), K0, AXIS)
    np.testing.assert_allclose(got, d - d[K0], atol=1e-12)
    assert abs(float(got[-1] - (d[-1] - d[K0])) * 1000) < 1e-9  # in mm too (the fit converts units)
    # Relative to a body that moves and turns (COMMON): the point's motion in that body's frame.
    q_other = quat_mul(COMMON, jnp.broadcast_to(Q0, (T, 4)))
    pos_other = jnp.stack([0.3 * TIME, 0.1 * jnp.sin(TIME), -0.2 * TIME**2], -1)
    r = jnp.array([0.05, 0.3, 0.02]) + d[:, None] * AXIS + e[:, None] * PERP  # in O's frame
    point = pos_other + quat_rotate(q_other, r)
    pos = point - quat_rotate(q_body, jnp.broadcast_to(lever, (T, 3)))
    axis_world = quat_rotate(q_other[K0], AXIS)
    got = body_displacement(pos, q_body, lever, pos_other, q_other, K0, axis_world)
    np.testing.assert_allclose(got, d - d[K0], atol=1e-12)


def test_observable_gradients_match_finite_differences():
    """d/dz of a weighted sum of both observables along paths that depend on parameters z,
    against central differences (both are used inside the fit's jacfwd/grad)."""
    weights = jnp.linspace(0.5, 1.5, T)

    def paths(z):
        q_other = quat_mul(quat_exp(TIME[:, None] * jnp.array([z[0], -0.6, 0.8])), jnp.broadcast_to(Q0, (T, 4)))
        q_rel = quat_mul(rot(PERP, z[1] * TIME**2), rot(AXIS, z[2] * jnp.sin(3.0 * TIME)))
        q_body = quat_mul(q_other, q_rel)
        pos_other = jnp.stack([z[3] * TIME, 0.1 * jnp.sin(TIME), -0.2 * TIME**2], -1)
        pos = pos_other + quat_rotate(q_other, jnp.array([0.05, 0.3, 0.02]) + z[3] * TIME[:, None] * PERP)
        return q_body, q_other, pos, pos_other

    def objective(z):
        q_body, q_other, pos, pos_other = paths(z)
        a = body_angle(q_body, q_other, K0, AXIS) + body_angle(q_body, identity_quats(T), K0, PERP)
        u = body_displacement(pos, q_body, jnp.array([0.0, 0.1, 0.02]), pos_other, q_other, K0, AXIS)
        return jnp.sum(weights * (a + u))

    z = jnp.array([1.1, 0.4, 0.9, 0.3])
    grad = np.asarray(jax.grad(objective)(z))
    eps = 1e-6
    fd = np.array([(objective(z + eps * e) - objective(z - eps * e)) / (2 * eps) for e in np.eye(4)])
    assert np.all(np.abs(grad) > 1e-3)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.jacfwd(objective)(z)), grad, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Fits: two pushes, two targets, one file per case (the angle) and a case column (the position)

H, START, DURATION = 1.0 / 60.0, 0.5, 0.5
TRUE, OTHER = (300.0, 15.0), (200.0, 25.0)
PUSH = dict(kind="force", body="Chest2", point=[0.0, 0.1, 0.0], direction=[0.0, 0.0, 1.0], magnitude=300.0,
            start=0.55, duration=0.1, shape="half_sine")
CASES = [PUSH, dict(PUSH, direction=[1.0, 0.0, 0.0], magnitude=200.0, start=0.6)]
ONSETS = [0.55, 0.6]
ANGLE = dict(kind="body_angle", body="head", axis="left", time_unit="ms", angle_unit="deg")
POSITION = dict(kind="body_position", body="head", relative_to="chest", point=[0.0, 0.1, 0.0], axis="forward",
                time_unit="ms", length_unit="mm")
SD_DEG = np.linspace(0.5, 1.0, 31)  # the angle corridor widens with time
SD_MM = 2.0


def config(files=("a0.csv", "a1.csv"), position=None, cases=CASES, **fit):
    pos = dict(POSITION, **({"file": "p.csv"} if position is None else {"files": list(position)}))
    return {"clip": str(CLIPS["mocapbank"]), "sim": {"start": START, "duration": DURATION, "h": H},
            "gains": {"ks": 2 * TRUE[0], "kd": TRUE[1] / 2}, "perturbation": [dict(c) for c in cases],
            "fit": {**fit, "target": [dict(ANGLE, files=list(files)), pos]}}


def write_targets(folder, curves, grid, onsets=ONSETS, prefix=""):
    """Corridors of simulated curves (C, T, 2) in the files' units, times in ms from each onset:
    the angle one file per case, the position one file with a case column (and, for configs that
    name one file per case, one per case too)."""
    for c in range(curves.shape[0]):
        t = grid - onsets[c]
        write_series_csv(folder / f"{prefix}a{c}.csv", t, np.rad2deg(curves[c, :, 0]), SD_DEG, "head", "ms")
        write_series_csv(folder / f"{prefix}p{c}.csv", t, 1000 * curves[c, :, 1], SD_MM, "head_chest", "ms")
    rows = ["case,time,head_chest,head_chest.sd"]
    rows += [f"{c},{float(1000 * (t - onsets[c]))!r},{float(1000 * curves[c, k, 1])!r},{SD_MM}"
             for c in range(curves.shape[0]) for k, t in enumerate(grid.tolist())]
    (folder / f"{prefix}p.csv").write_text("\n".join(rows) + "\n")


@pytest.fixture(scope="module")
def bank():
    return load_character(CLIPS["mocapbank"])


@pytest.fixture(scope="module")
def bench(bank, tmp_path_factory):
    """The problem (from files of zeros spanning more than the simulation), its compiled
    evaluator, and the curves at the two known gain pairs."""
    folder = tmp_path_factory.mktemp("body_targets")
    grid = START + H * np.arange(31)
    write_targets(folder, np.zeros((2, grid.size, 2)), grid)
    cal = F.calibration_from_dict(config(), "bench.toml", folder, character=bank[0], traj=bank[1])
    ev = F.ResponseEvaluator(cal.problem)
    truth, other = ev(np.log(TRUE)), ev(np.log(OTHER))
    assert np.all(truth.diverged == -1) and np.all(other.diverged == -1)
    return cal, ev, truth.curves, other.curves


def test_targets_read_in_their_units_on_each_cases_clock(bench, tmp_path, bank):
    """Files in deg and mm with times in ms from each case's onset give the target in rad and m
    on the clip's clock; the corridor weighs by 1/sd; the same series in seconds of clip time
    (time_offset = 0) give the same target."""
    cal, ev, curves, _ = bench
    grid = cal.time
    assert cal.problem.spec.kind == "multiple" and grid.size == 31 and abs(grid[0] - START) < 1e-12
    write_targets(tmp_path, curves, grid)
    here = F.calibration_from_dict(config(), "t.toml", tmp_path, character=bank[0], traj=bank[1])
    np.testing.assert_allclose(here.target, curves.reshape(-1), rtol=0, atol=1e-12)
    w = here.weights.reshape(2, 31, 2)
    np.testing.assert_allclose(w[..., 0], np.broadcast_to(1.0 / np.deg2rad(SD_DEG), (2, 31)), rtol=1e-9)
    np.testing.assert_allclose(w[..., 1], 1.0 / (SD_MM / 1000), rtol=1e-12)
    assert [b["unit"] for b in here.blocks] == ["deg", "mm"] and here.leave_one_out
    # Seconds of clip time: time_offset = 0 puts the file's time 0 at clip time 0.
    for c in range(2):
        write_series_csv(tmp_path / f"s{c}.csv", grid, np.rad2deg(curves[c, :, 0]), SD_DEG, "pitch", "s")
    data = config(files=("s0.csv", "s1.csv"))
    data["fit"]["target"][0].update(time_unit="s", time_offset=0.0)
    again = F.calibration_from_dict(data, "t.toml", tmp_path, character=bank[0], traj=bank[1])
    np.testing.assert_allclose(again.target, here.target, rtol=0, atol=1e-12)


def test_model_output_gradient_matches_central_differences(bench):
    cal, ev, _, _ = bench
    x = np.log(TRUE) + np.array([0.1, -0.2])
    jac = ev(x).jac
    eps = 1e-5
    fd = np.stack([(ev(x + eps * e).y - ev(x - eps * e).y) / (2 * eps) for e in np.eye(2)], 1)
    assert np.linalg.norm(jac[:, 0]) > 0 and np.linalg.norm(jac[:, 1]) > 0
    np.testing.assert_allclose(jac, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def test_two_targets_two_subjects_fit_back_the_known_gains(bench, tmp_path, bank):
    """Corridors simulated at ks = 300, kd = 15, fitted from ks 2x too high and kd 2x too low."""
    cal, ev, curves, _ = bench
    write_targets(tmp_path, curves, cal.time)
    here = F.calibration_from_dict(config(leave_one_out=False), "rt.toml", tmp_path, character=bank[0],
                                   traj=bank[1])
    assert not here.leave_one_out
    res, doc = F.calibrate(here, tmp_path / "out", progress=False, evaluator=ev.with_problem(here.problem))
    assert res.status == "converged" and res.iterations >= 2
    np.testing.assert_allclose([res.ks, res.kd], TRUE, rtol=0.01)
    np.testing.assert_allclose([res.ks, res.kd], TRUE, rtol=1e-6)  # exact data: in fact to round-off
    assert "leave_one_out" not in doc
    assert [t["kind"] for t in doc["targets"]] == ["body_angle", "body_position"]
    for row in doc["case_errors"]:
        assert all(e["rms"] < 1e-6 and e["rms_sd"] < 1e-6 for e in row["fitted"])
    png = (tmp_path / "out" / "fit.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_leave_one_out_equals_a_fit_on_the_other_case(bench, tmp_path, bank, capsys):
    """Case 0 simulated at (300, 15), case 1 at (200, 25): leaving case 0 out fits case 1 alone,
    which gives (200, 25), and predicts case 0 with the error of that pair's rollout against case
    0's target; the same as a direct fit of case 1's data alone (a config of it twice)."""
    from neuromotor.cli import main

    cal, ev, truth, other = bench
    mixed = np.stack([truth[0], other[1]])
    write_targets(tmp_path, mixed, cal.time)
    (tmp_path / "fit.toml").write_text(_toml(config()))
    assert main(["fit", str(tmp_path / "fit.toml"), "-o", str(tmp_path / "out"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "leave-one-out: case 0 predicted by a fit on the others" in out
    doc = json.loads((tmp_path / "out" / "fit.json").read_text())
    loo = doc["leave_one_out"]
    assert [r["case"] for r in loo] == [0, 1] and all(r["status"] == "converged" for r in loo)
    np.testing.assert_allclose([loo[0]["values"]["ks"], loo[0]["values"]["kd"]], OTHER, rtol=1e-6)
    np.testing.assert_allclose([loo[1]["values"]["ks"], loo[1]["values"]["kd"]], TRUE, rtol=1e-6)
    # Case 0 predicted at (200, 25): its rollout against case 0's target, in deg and mm, and in sds.
    miss = other[0] - truth[0]
    want_deg = np.sqrt(np.mean(np.rad2deg(miss[:, 0]) ** 2))
    want_sd = np.sqrt(np.mean((np.rad2deg(miss[:, 0]) / SD_DEG) ** 2))
    angle, position = loo[0]["predicted"]
    assert angle["unit"] == "deg" and position["unit"] == "mm" and want_deg > 0.5
    np.testing.assert_allclose([angle["rms"], angle["rms_sd"]], [want_deg, want_sd], rtol=1e-5)
    np.testing.assert_allclose(position["rms"], np.sqrt(np.mean((1000 * miss[:, 1]) ** 2)), rtol=1e-5)
    np.testing.assert_allclose(position["rms_sd"], position["rms"] / SD_MM, rtol=1e-9)
    # Worse than the fit on both cases predicts it (that one saw case 0).
    assert angle["rms"] > doc["case_errors"][0]["fitted"][0]["rms"]
    # A direct fit of case 1's data alone: the perturbation and its files twice.
    direct = config(files=("a1.csv", "a1.csv"), position=("p1.csv", "p1.csv"), cases=[CASES[1], CASES[1]])
    alone = F.calibration_from_dict(direct, "d.toml", tmp_path, character=bank[0], traj=bank[1])
    res, _ = F.calibrate(alone, None, progress=False, evaluator=ev.with_problem(alone.problem))
    np.testing.assert_allclose([res.ks, res.kd], [loo[0]["values"]["ks"], loo[0]["values"]["kd"]], rtol=1e-6)
    both = F.calibration_from_dict(config(), "m.toml", tmp_path, character=bank[0], traj=bank[1])
    pred = both.errors(ev.with_problem(both.problem)(res.x).y, both.case_index() == 0)
    for got, want in zip(loo[0]["predicted"], pred):
        assert got["n"] == want["n"] == 31
        np.testing.assert_allclose([got["rms"], got["rms_sd"]], [want["rms"], want["rms_sd"]], rtol=1e-5)


def _toml(data) -> str:
    """The few shapes of config() as TOML."""
    def val(v):
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(float(v)) if isinstance(v, float) else str(v)

    lines = [f"clip = {val(data['clip'])}"]
    for table in ("sim", "gains"):
        lines += [f"[{table}]"] + [f"{k} = {val(v)}" for k, v in data[table].items()]
    for p in data["perturbation"]:
        lines += ["[[perturbation]]"] + [f"{k} = {val(v)}" for k, v in p.items()]
    lines += ["[fit]"] + [f"{k} = {val(v)}" for k, v in data["fit"].items() if k != "target"]
    for t in data["fit"]["target"]:
        lines += ["[[fit.target]]"] + [f"{k} = {val(v)}" for k, v in t.items()]
    return "\n".join(lines) + "\n"


def test_joint_angle_files_per_case_mix_with_a_body_target(tmp_path, bank):
    """``files = [...]`` for a joint-angle target too (each file one case, own times), fitted
    beside a body target: the model output and the target line up (shapes traced, nothing
    compiled), each case interpolated from its own file."""
    grid = START + H * np.arange(31)
    write_targets(tmp_path, np.zeros((2, grid.size, 2)), grid)
    times = [np.linspace(0.4, 1.1, 8), np.linspace(0.45, 1.05, 13)]
    for c, t in enumerate(times):
        rows = ["time,Chest.Xrotation,Neck.Xrotation"] + [f"{x!r},{10 * c + x!r},{-x!r}" for x in t.tolist()]
        (tmp_path / f"j{c}.csv").write_text("\n".join(rows) + "\n")
    data = config()
    data["fit"]["target"].append({"kind": "joint_angles", "files": ["j0.csv", "j1.csv"], "angle_unit": "deg",
                                  "weights": {"Neck.Xrotation": 2.0}})
    cal = F.calibration_from_dict(data, "j.toml", tmp_path, character=bank[0], traj=bank[1])
    y = jax.eval_shape(lambda x: cal.problem.outputs(x)[0], jnp.zeros(2))
    assert cal.problem.spec.kind == "multiple" and y.shape == cal.target.shape == cal.weights.shape == (2 * 31 * 4,)
    tgt, w = cal.target.reshape(2, 31, 4), cal.weights.reshape(2, 31, 4)
    for c in range(2):  # linear in time: interpolation is exact
        np.testing.assert_allclose(tgt[c, :, 2], np.deg2rad(10 * c + grid), rtol=1e-12)
        np.testing.assert_allclose(tgt[c, :, 3], np.deg2rad(-grid), rtol=1e-12)
    assert np.all(w[..., 2] == 1.0) and np.all(w[..., 3] == 2.0)
    assert cal.labels == ("head: angle about left", "head rel. chest: displacement along forward",
                          "Chest.Xrotation", "Neck.Xrotation")
    assert [b["columns"] for b in cal.blocks] == [(0, 1), (1, 2), (2, 4)]
    (tmp_path / "j1.csv").write_text("case,time,Chest.Xrotation,Neck.Xrotation\n0,0.4,0,0\n0,1.1,0,0\n"
                                     "1,0.4,0,0\n1,1.1,0,0\n")
    with pytest.raises(ConfigError, match=r"j1\.csv: holds 2 cases; each of files = \[\.\.\.\] gives one case"):
        F.calibration_from_dict(data, "j.toml", tmp_path, character=bank[0], traj=bank[1])


# ---------------------------------------------------------------------------------------------
# Config and file errors: one line naming the file and the field (and the line)


def _cfg(n=2):
    return simulation_config({"perturbation": [dict(c) for c in CASES[:n]]}, "f.toml")


def test_several_targets_and_per_case_files_parse(tmp_path):
    spec = fit_spec(config(), _cfg(), tmp_path)
    angle, position = spec.targets
    assert spec.target is angle and spec.leave_one_out is None
    assert angle.kind == "body_angle" and angle.files == (tmp_path / "a0.csv", tmp_path / "a1.csv")
    assert angle.axis == "left" and angle.relative_to == "world" and angle.time_offset is None
    assert angle.time_unit == "ms" and angle.angle_unit == "deg" and angle.paths == angle.files
    assert position.file == tmp_path / "p.csv" and position.point == (0.0, 0.1, 0.0)
    assert position.length_unit == "mm" and position.relative_to == "chest" and position.axis == "forward"
    # The single [fit.target] table still reads, with a vector axis.
    one = fit_spec({"fit": {"target": dict(ANGLE, file="a.csv", axis=[0, 0, 2])}}, _cfg(), tmp_path)
    assert one.targets == (one.target,) and one.target.axis == (0.0, 0.0, 2.0)


@pytest.mark.parametrize("change, match", [
    (dict(time_unit="min"), r"field 'fit\.target\[0\]\.time_unit' must be one of \['s', 'ms'\]"),
    (dict(time_unit=None), r"field 'fit\.target\[0\]\.time_unit' is required: one of \['s', 'ms'\]"),
    (dict(angle_unit=None), r"field 'fit\.target\[0\]\.angle_unit' is required"),
    (dict(angle_unit="grad"), r"field 'fit\.target\[0\]\.angle_unit' must be one of \['deg', 'rad'\]"),
    (dict(length_unit="mm"), r"field 'fit\.target\[0\]\.length_unit' does not apply to kind = 'body_angle'"),
    (dict(files=["a0.csv"]), r"field 'fit\.target\[0\]\.files' has 1 entries but there are 2 \[\[perturbation\]\]"),
    (dict(file="a.csv"), r"field 'fit\.target\[0\]\.file' or 'files' is required \(not both\)"),
    (dict(files=["a0.txt", "a1.txt"]), r"field 'fit\.target\[0\]\.files\[0\]' must be a \.csv file"),
    (dict(axis="sideways"), r"field 'fit\.target\[0\]\.axis' must be 3 numbers or one of"),
    (dict(body=None), r"field 'fit\.target\[0\]\.body' is required"),
    (dict(point=[0, 0, 0]), r"field 'fit\.target\[0\]\.point' applies to kind = 'body_position' only"),
])
def test_bad_body_target_fields_are_named(tmp_path, change, match):
    data = config()
    target = data["fit"]["target"][0]
    for k, v in change.items():
        if v is None:
            target.pop(k)
        else:
            target[k] = v
    with pytest.raises(ConfigError, match=r"^f\.toml: " + match):
        fit_spec(data, _cfg(), tmp_path)


def test_bad_fit_combinations_are_named(tmp_path):
    data = config()
    data["fit"]["target"].append({"kind": "features", "case": [{"peak_deviation_deg": {"value": 1, "sd": 1,
                                                                                       "source": "x"}}] * 2})
    with pytest.raises(ConfigError, match=r"field 'fit\.target\[2\]\.kind' = 'features' cannot be fitted together"):
        fit_spec(data, _cfg(), tmp_path)
    with pytest.raises(ConfigError, match=r"field 'fit\.leave_one_out' needs 2 or more \[\[perturbation\]\] cases"):
        fit_spec({"fit": {"leave_one_out": True, "target": dict(ANGLE, file="a.csv")}}, _cfg(1), tmp_path)
    data = config()
    data["fit"]["target"][1]["angle_unit"] = "deg"
    with pytest.raises(ConfigError, match=r"field 'fit\.target\[1\]\.angle_unit' does not apply to kind = "
                                          r"'body_position' \(its unit field is 'length_unit'\)"):
        fit_spec(data, _cfg(), tmp_path)


def test_bad_target_files_name_the_file_and_line(tmp_path):
    def read(text, name="t.csv", **kw):
        (tmp_path / name).write_text(text)
        return read_series([tmp_path / name], "ms", **kw)

    with pytest.raises(ConfigError, match=r"t\.csv: field 'time' column is missing"):
        read("t,head\n0,1\n1,2\n")
    with pytest.raises(ConfigError, match=r"t\.csv: line 4: field 'time' = 10 is not after the previous 20"):
        read("# a comment\ntime,head\n20,1\n10,2\n")
    with pytest.raises(ConfigError, match=r"t\.csv: line 3: field 'head\.sd' must be > 0, got '0'"):
        read("time,head,head.sd\n0,1,1\n10,2,0\n")
    with pytest.raises(ConfigError, match=r"t\.csv: line 2: field 'head' is not a number: 'abc'"):
        read("time,head\n0,abc\n10,2\n")
    with pytest.raises(ConfigError, match=r"t\.csv: field 'neck\.sd' has no mean column"):
        read("time,head,neck.sd\n0,1,1\n10,2,1\n")
    with pytest.raises(ConfigError, match=r"t\.csv: has 2 data columns \['head', 'neck'\]; name the one"):
        read("time,head,neck\n0,1,1\n10,2,1\n")
    assert read("time,head,neck\n0,1,1\n10,2,3\n", column="neck")[0].value.tolist() == [1.0, 3.0]
    with pytest.raises(ConfigError, match=r"t\.csv: holds 1 case\(s\) but there are 2 \[\[perturbation\]\]"):
        read("time,head\n0,1\n10,2\n", n_cases=2)
    got = read("case,time,head\n0,0,1\n0,10,2\n1,-5,3\n1,5,4\n1,15,5\n", n_cases=2)
    assert [s.time.tolist() for s in got] == [[0.0, 0.01], [-0.005, 0.005, 0.015]]
    (tmp_path / "a.csv").write_text("time,head,head.sd\n0,1,1\n10,2,1\n")
    (tmp_path / "b.csv").write_text("time,head\n0,1\n10,2\n")
    with pytest.raises(ConfigError, match=r"b\.csv: field 'head\.sd' column is missing but .*a\.csv has one"):
        read_series([tmp_path / "a.csv", tmp_path / "b.csv"], "ms")


def test_unknown_body_is_named(tmp_path, bank):
    grid = START + H * np.arange(31)
    write_targets(tmp_path, np.zeros((2, grid.size, 2)), grid)
    data = config()
    data["fit"]["target"][1]["relative_to"] = "Skull"
    with pytest.raises(ConfigError, match=r"^b\.toml: field 'fit\.target\[1\]\.relative_to': unknown body "
                                          r"'Skull'; bodies are Hips, "):
        F.calibration_from_dict(data, "b.toml", tmp_path, character=bank[0], traj=bank[1])


def test_cli_bad_target_file_is_one_line_exit_2(tmp_path, capsys):
    from neuromotor.cli import main

    grid = START + H * np.arange(31)
    write_targets(tmp_path, np.zeros((2, grid.size, 2)), grid)
    (tmp_path / "a1.csv").write_text("time,head\n0,1\n-10,2\n")
    (tmp_path / "fit.toml").write_text(_toml(config()))
    assert main(["fit", str(tmp_path / "fit.toml"), "-o", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "a1.csv: line 3: field 'time' = -10 is not after the previous 0" in err
    assert not (tmp_path / "out").exists()
