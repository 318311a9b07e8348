"""Issue 5: batch sweeps sharded over devices, the sweep table, plots, config errors and the CLI.

Compiles are the cost here: one sweep program for the 19-joint clip (module fixture; the CLI test
reuses it through the persistent compile cache) and, in a subprocess with two forced host
devices, three small programs on a 4-body clip.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.studies import sweep as sw
from neuromotor.config import DEFAULT_HIT, ConfigError, SimulationConfig, simulation_config
from neuromotor.studies.simulate import body_lookup, load_character, prepare

TESTS = pathlib.Path(__file__).resolve().parent


def tiny_bvh(path: pathlib.Path, frames: int = 60) -> pathlib.Path:
    """A 4-body clip (hips, chest, upper arm, forearm) with smooth motion, in cm."""
    hierarchy = textwrap.dedent("""\
        HIERARCHY
        ROOT Hips
        {
          OFFSET 0 90 0
          CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
          JOINT Chest
          {
            OFFSET 0 10 0
            CHANNELS 3 Zrotation Xrotation Yrotation
            JOINT Arm
            {
              OFFSET 15 30 0
              CHANNELS 3 Zrotation Xrotation Yrotation
              JOINT Forearm
              {
                OFFSET 28 0 0
                CHANNELS 3 Zrotation Xrotation Yrotation
                End Site
                {
                  OFFSET 25 0 0
                }
              }
            }
          }
        }
        MOTION
        """)
    t = np.arange(frames) / 30.0
    rows = [[0, 90, 0, 0, 0, 0, 5 * np.sin(2 * s), 3 * np.cos(s), 0, -20 + 15 * np.sin(3 * s),
             10 * np.sin(2 * s), 0, 30 + 20 * np.sin(2.5 * s), 0, 5 * np.cos(s)] for s in t]
    body = "\n".join(" ".join(f"{v:.5f}" for v in r) for r in rows)
    path.write_text(hierarchy + f"Frames: {frames}\nFrame Time: 0.0333333\n{body}\n")
    return path


# Runs in a fresh interpreter so that the forced device count applies before jax is imported.
SHARDED_SCRIPT = textwrap.dedent("""\
    import dataclasses, json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from neuromotor.studies import sweep as sw, metrics as mx
    from neuromotor.config import DEFAULT_HIT, SimulationConfig
    from neuromotor.studies.simulate import body_lookup, load_character, prepare, run

    character, traj = load_character(sys.argv[1])
    hit = dict(DEFAULT_HIT, body="Forearm", point=[0.1, 0.0, 0.0], magnitude=20.0, start=0.2)
    cfg = SimulationConfig(duration=1.2, perturbations=[hit])
    s = prepare(cfg, character, traj)
    spec = sw.SweepSpec([0.0, 15.0, 30.0, 1e6], [sw.GainSetting(400.0, 20.0), sw.GainSetting(150.0, 8.0)])
    runs = spec.runs(hit)  # 8 runs in chunks of 6: the second chunk is padded
    index = body_lookup(s.model)
    out = {"devices": len(jax.devices())}
    for name, devs in (("sharded", jax.devices()), ("single", jax.devices()[:1])):
        sweeper = sw.Sweeper(s.model, s.ref, s.options, chunk=6, mesh=sw.device_mesh(devs))
        res = sw.run_sweep(sweeper, s.gains, s.pulses, runs, index, s.model.body_names,
                           keep_curves=True, progress=False)
        chunk_out = sweeper.simulate_chunk(sweeper.pad(sw.build_batch(s.gains, s.pulses, runs, index, s.options.h, s.model), 0, 6))
        out[name] = {"curves": res.curves.tolist(), "rows": res.rows,
                     "shards": len({sh.device for sh in chunk_out.pose.addressable_shards})}
    # Rollouts vmapped three at a time: the sweep switches to the batched solver (branch).
    sweeper = sw.Sweeper(s.model, s.ref, s.options, chunk=6, inner_batch=3, mesh=sw.device_mesh(jax.devices()[:1]))
    res = sw.run_sweep(sweeper, s.gains, s.pulses, runs, index, s.model.body_names, keep_curves=True, progress=False)
    out["batched"] = {"curves": res.curves.tolist(), "rows": res.rows, "solver": str(sweeper.options.solver)}
    # One run of the grid through the ordinary single-run path.
    i = 5  # gains (150, 8), magnitude 15
    one = prepare(SimulationConfig(duration=1.2, ks=150.0, kd=8.0, perturbations=[dict(hit, magnitude=15.0)]),
                  character, traj)
    r = run(one)
    out["single_run"] = {"index": i, "metrics": r.metrics,
                         "curve": np.asarray(mx.joint_deviation(one.model, r.perturbed.states.quat,
                                                                   r.unperturbed.states.quat)).tolist()}
    # A batch split over the devices (bench's batches): equal to the plain vmap, one share per device.
    from neuromotor.physics import dynamics as dy
    from neuromotor.studies.sweep import runner
    bsim = dataclasses.replace(s.options, solver="branch", n_steps=40)
    mags = np.linspace(0.5, 1.5, 4)[:, None] * np.asarray(s.pulses.magnitude)[None]
    one = lambda mag, sh: dy.rollout(s.model, sh[0], dataclasses.replace(s.pulses, magnitude=mag), sh[1], bsim).theta
    mesh = runner.batch_mesh(4, bsim)
    split = jax.jit(runner.shard_vmap(one, mesh))(mags, (s.gains, s.ref))
    plain = jax.jit(runner.shard_vmap(one, None))(mags, (s.gains, s.ref))
    lapack = lambda **kw: dataclasses.replace(s.options, **kw)
    out["split"] = {"diff": float(np.max(np.abs(np.asarray(split) - np.asarray(plain)))),
                    "spread": float(np.max(np.abs(np.asarray(plain)[0] - np.asarray(plain)[3]))),
                    "shards": len({sh.device for sh in split.addressable_shards}),
                    "mesh": [None if m is None else int(m.devices.size) for m in (
                        mesh, runner.batch_mesh(3, bsim), runner.batch_mesh(4, lapack(driven=(2,))),
                        runner.batch_mesh(4, lapack(free_root=True)), runner.batch_mesh(4, lapack(solver="dense")),
                        runner.batch_mesh(4, lapack(solver="tree")))],
                    "sweeper": [int(sw.Sweeper(s.model, s.ref, sim, chunk=4).mesh.devices.size)
                                for sim in (s.options, lapack(driven=(2,)))]}
    print("RESULT" + json.dumps(out))
    """)


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    clip = tiny_bvh(tmp_path_factory.mktemp("tiny") / "tiny.bvh")
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", SHARDED_SCRIPT, str(clip)], env=env, cwd=TESTS,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")][-1]
    return json.loads(line[len("RESULT"):])


def test_sharded_sweep_equals_unsharded(sharded):
    assert sharded["devices"] == 2
    assert sharded["sharded"]["shards"] == 2 and sharded["single"]["shards"] == 1
    a, b = np.array(sharded["sharded"]["curves"]), np.array(sharded["single"]["curves"])
    assert a.shape == (8, 145)  # every run, padding dropped; 1.2 s at 1/120 s
    # Equal up to rounding: the two programs are compiled separately (fusion may reorder sums).
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    assert a[1].max() > 1.0  # and not trivially: the runs do deflect
    for ra, rb in zip(sharded["sharded"]["rows"], sharded["single"]["rows"]):
        assert ra["diverged"] == rb["diverged"]
        for k in sw.METRIC_KEYS:
            np.testing.assert_allclose(ra[k], rb[k], rtol=1e-9, err_msg=k)  # NaN == NaN here


def test_a_batch_split_over_devices_equals_one_vmap_and_keeps_lapack_on_one_device(sharded):
    split = sharded["split"]
    assert split["shards"] == 2
    assert split["diff"] < 1e-12 and split["spread"] > 1e-3  # equal, and the runs differ
    # 2 devices for the null-space and tree steps; none (one vmap) for a batch that does not divide
    # or for steps that call LAPACK (driven joints, a free root, the dense solver): see uses_lapack.
    assert split["mesh"] == [2, None, None, None, None, 2]
    assert split["sweeper"] == [2, 1]


def test_vmapped_sweep_uses_the_batched_solver_and_equals_the_looped_one(sharded):
    assert sharded["batched"]["solver"] == "branch"
    a, b = np.array(sharded["batched"]["curves"]), np.array(sharded["single"]["curves"])
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    assert [r["diverged"] for r in sharded["batched"]["rows"]] == [r["diverged"] for r in sharded["single"]["rows"]]


def test_sweep_row_matches_single_run(sharded):
    one = sharded["single_run"]
    row = sharded["sharded"]["rows"][one["index"]]
    assert (row["ks"], row["kd"], row["magnitude"]) == (150.0, 8.0, 15.0)
    np.testing.assert_allclose(sharded["sharded"]["curves"][one["index"]], one["curve"], rtol=0, atol=1e-9)
    for k in ("peak_deviation_deg", "time_of_peak_s", "recovery_time_s"):
        np.testing.assert_allclose(row[k], one["metrics"][k], rtol=1e-9)
    assert math.isfinite(row["recovery_time_s"])  # the small clip's arm recovers within the window


def test_sharded_rows_mark_divergence(sharded):
    rows = sharded["sharded"]["rows"]
    for r in rows:
        blown = r["magnitude"] >= 1e6
        assert r["diverged"] == blown
        if blown:
            assert r["diverged_step"] >= 0 and r["diverged_body"] in ("Chest", "Arm", "Forearm")
            assert all(math.isnan(r[k]) for k in sw.METRIC_KEYS)
        else:
            assert r["diverged_step"] == -1 and math.isfinite(r["peak_deviation_deg"])


# ------------------------------------------------------------------------- the 19-joint clip

WINDOW = dict(duration=0.5)
HIT = dict(DEFAULT_HIT, body="Chest2", start=0.1)
MAGS = [0.0, 150.0, 300.0, 1e7]
GAINS = [(400.0, 20.0), (100.0, 10.0)]


@pytest.fixture(scope="module")
def bank_sweep():
    character, traj = load_character(CLIPS["mocapbank"])
    cfg = SimulationConfig(perturbations=[HIT], **WINDOW)
    s = prepare(cfg, character, traj)
    spec = sw.SweepSpec(MAGS, [sw.GainSetting(*g) for g in GAINS])
    sweeper = sw.Sweeper(s.model, s.ref, s.options, chunk=8)
    return sw.run_sweep(sweeper, s.gains, s.pulses, spec.runs(HIT), body_lookup(s.model),
                        s.model.body_names, keep_curves=True, progress=False)


def test_real_clip_peaks_grow_with_magnitude_and_softness(bank_sweep):
    rows = bank_sweep.rows
    assert len(rows) == len(MAGS) * len(GAINS)
    by = {(r["ks"], r["magnitude"]): r for r in rows}
    for ks, _ in GAINS:
        assert by[(ks, 0.0)]["peak_deviation_deg"] == 0.0
        assert 0.5 < by[(ks, 150.0)]["peak_deviation_deg"] < by[(ks, 300.0)]["peak_deviation_deg"]
        assert HIT["start"] < by[(ks, 300.0)]["time_of_peak_s"] <= HIT["start"] + 0.4
    # Softer muscles deflect further under the same hit.
    assert by[(100.0, 300.0)]["peak_deviation_deg"] > by[(400.0, 300.0)]["peak_deviation_deg"]
    # Nothing moves before the hit.
    before = bank_sweep.time < HIT["start"]
    assert np.abs(bank_sweep.curves[:, before]).max() < 1e-9


def test_real_clip_diverged_runs_are_kept_and_marked(bank_sweep):
    for r in bank_sweep.rows:
        if r["magnitude"] >= 1e7:
            assert r["diverged"] and r["diverged_step"] >= 0 and r["diverged_body"]
            assert math.isnan(r["peak_deviation_deg"])
        else:
            assert not r["diverged"]
            assert r["max_kkt_residual"] < 1e-8 and r["max_constraint_violation"] < 1e-8


def test_csv_round_trip_and_plots(bank_sweep, tmp_path):
    path = sw.write_csv(bank_sweep.rows, tmp_path / "sweep.csv")
    back = sw.read_csv(path)
    assert [r["run"] for r in back] == list(range(len(bank_sweep.rows)))
    for a, b in zip(back, bank_sweep.rows):
        for k in sw.COLUMNS:
            assert a[k] == b[k] or (isinstance(b[k], float) and math.isnan(a[k]) and math.isnan(b[k])), k
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    import matplotlib.image as mpimg

    png = sw.plot_sweep(back, tmp_path / "sweep.png")
    img = mpimg.imread(png)
    assert img.shape[0] > 200 and img.shape[1] > 400 and img[..., :3].std() > 0.05


def test_gains_map_marks_fitted_pair_and_bad_cells(tmp_path):
    rows = []
    for i, ks in enumerate([100.0, 400.0, 1600.0]):
        for j, kd in enumerate([5.0, 20.0]):
            bad = i == 0 and j == 0
            rows.append({"ks": ks, "kd": kd, "diverged": bad,
                         "recovery_time_s": math.nan if bad else 1.0 / (1 + i + j),
                         "peak_deviation_deg": math.nan if bad else 10.0 / (1 + i)})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from neuromotor.viz import sweep_plots

    captured = {}
    orig = sweep_plots.save_figure
    try:
        sweep_plots.save_figure = lambda fig, path: captured.setdefault("fig", fig) and orig(fig, path)
        sweep_plots.plot_gains_map(rows, tmp_path / "map.png", fitted=(400.0, 20.0))
    finally:
        sweep_plots.save_figure = orig
    ax = captured["fig"].axes[0]
    star = [ln for ln in ax.lines if ln.get_marker() == "*"]
    cross = [ln for ln in ax.lines if ln.get_marker() == "x"]
    assert len(star) == 1 and tuple(star[0].get_xydata()[0]) == (400.0, 20.0)
    assert len(cross) == 1 and tuple(cross[0].get_xydata()[0]) == (100.0, 5.0)
    assert (tmp_path / "map.png").stat().st_size > 5000
    plt.close("all")


def test_sweep_config_errors_name_file_and_field(tmp_path):
    base = {"perturbation": [dict(DEFAULT_HIT)]}

    def spec(table):
        data = dict(base, sweep=table)
        return sw.sweep_spec(data, simulation_config(data, "s.toml"))

    with pytest.raises(ConfigError, match=r"s\.toml: field 'sweep\.magnitudes'"):
        spec({"magnitudes": "big"})
    with pytest.raises(ConfigError, match=r"s\.toml: field 'sweep\.magnitudes\.num'"):
        spec({"magnitudes": {"start": 0.0, "stop": 1.0, "num": 0}})
    with pytest.raises(ConfigError, match=r"sweep\.gains\[0\]\.controller"):
        spec({"gains": [{"ks": 1.0, "controller": "robot"}]})
    with pytest.raises(ConfigError, match=r"sweep\.chunk"):
        spec({"chunk": 0})
    with pytest.raises(ConfigError, match=r"sweep\.magnitude\b"):
        spec({"magnitude": [1.0]})
    with pytest.raises(ConfigError, match=r"field 'perturbation' is required"):
        sw.sweep_spec({"sweep": {}}, simulation_config({"sweep": {}}, "s.toml"))
    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps({"fitted": {"ks": 321.0, "kd": 12.5}, "loss": 0.1}))
    assert spec({"fitted": str(fit)}).fitted == (321.0, 12.5)
    with pytest.raises(ConfigError, match=r"sweep\.fitted"):
        spec({"fitted": str(tmp_path / "missing.json")})
    grid = spec({"magnitudes": {"start": 0.0, "stop": 300.0, "num": 4}, "ks": {"start": 100.0, "stop": 1600.0,
                                                                            "num": 3, "log": True}})
    assert grid.magnitudes == [0.0, 100.0, 200.0, 300.0]
    np.testing.assert_allclose([g.ks for g in grid.gains], [100.0, 400.0, 1600.0])


def test_cli_sweep_writes_table_and_plot(bank_sweep, tmp_path):
    from neuromotor.cli import main

    cfg = tmp_path / "sweep.toml"
    cfg.write_text(textwrap.dedent(f"""\
        clip = "{CLIPS['mocapbank']}"
        [sim]
        duration = {WINDOW['duration']}
        [[perturbation]]
        body = "{HIT['body']}"
        point = {HIT['point']}
        direction = {HIT['direction']}
        magnitude = 100.0
        start = {HIT['start']}
        [sweep]
        magnitudes = {MAGS}
        ks = [400.0, 100.0]
        kd = [20.0, 10.0]
        chunk = 8
        """))
    out = tmp_path / "out"
    assert main(["sweep", str(cfg), "-o", str(out), "--no-progress"]) == 0
    rows = sw.read_csv(out / "sweep.csv")
    assert len(rows) == 4 * len(MAGS)  # ks x kd x magnitudes
    ref = {(r["ks"], r["kd"], r["magnitude"]): r for r in bank_sweep.rows}
    for r in rows:
        if (r["ks"], r["kd"], r["magnitude"]) in ref and not r["diverged"]:
            np.testing.assert_allclose(r["peak_deviation_deg"],
                                       ref[(r["ks"], r["kd"], r["magnitude"])]["peak_deviation_deg"], rtol=1e-9)
    assert (out / "sweep.png").stat().st_size > 5000 and (out / "gains_map.png").stat().st_size > 5000
    assert main(["sweep", str(tmp_path / "nope.toml"), "-o", str(out)]) == 2


def test_experiment_configs_parse_and_errors_name_the_field(tmp_path):
    from neuromotor.studies.experiments import experiment_spec, load_experiment

    repo = TESTS.parents[1]
    for name, kind in (("exp_arm", "arm"), ("exp_full_body", "full_body"), ("exp_high_gain", "contrast")):
        cfg, exp = load_experiment(repo / "configs" / f"{name}.toml")
        assert exp.kind == kind and cfg.perturbations
    cfg, exp = load_experiment(repo / "configs" / "exp_arm.toml")
    assert cfg.perturbations[0]["body"] == "LeftElbow"
    free = {"Hips", "LeftShoulder", "LeftElbow", "LeftWrist"}
    assert set(cfg.driven_joints) == set(EXPECTED_BODIES) - free  # everything but the left arm
    cfg, exp = load_experiment(repo / "configs" / "exp_high_gain.toml")
    assert {g.controller for g in exp.controllers} == {"neuromotor", "pd"}
    for name in ("sweep_magnitude", "sweep_gains_map"):
        _, spec = sw.load_sweep_config(repo / "configs" / f"{name}.toml")
        assert len(spec.magnitudes) * len(spec.gains) > 1
    data = {"perturbation": [dict(DEFAULT_HIT)], "experiment": {"kind": "arm", "frames": 0}}
    with pytest.raises(ConfigError, match=r"e\.toml: field 'experiment\.frames'"):
        experiment_spec(data, simulation_config(data, "e.toml"))
    data["experiment"] = {"kind": "juggle"}
    with pytest.raises(ConfigError, match=r"experiment\.kind"):
        experiment_spec(data, simulation_config(data, "e.toml"))
    data["experiment"] = {"kind": "contrast", "controller": [{"controller": "pd", "kp": 1.0}]}
    with pytest.raises(ConfigError, match=r"experiment\.controller\[0\]\.kp"):
        experiment_spec(data, simulation_config(data, "e.toml"))


EXPECTED_BODIES = ["Hips", "Chest", "Chest2", "LeftCollar", "LeftShoulder", "LeftElbow", "LeftWrist",
                   "RightCollar", "RightShoulder", "RightElbow", "RightWrist", "Neck", "Head", "LeftHip",
                   "LeftKnee", "LeftAnkle", "RightHip", "RightKnee", "RightAnkle"]
