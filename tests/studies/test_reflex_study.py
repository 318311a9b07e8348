"""Issue 18: the reflex studies (studies/reflex.py). The stability grid on the 4-body clip (one
sweep compile): without a delayed path the hit is a stable recovery, a huge delayed gain blows
up and is flagged; the classification, the boundary table and the map on synthetic rows; the
three feedback-path controllers of the path comparison."""

from __future__ import annotations

import math

import pytest

from neuromotor.config import ReflexSpec, SimulationConfig
from neuromotor.studies import reflex as rs
from neuromotor.studies.simulate import load_character
from test_sweep import tiny_bvh

HIT = dict(kind="force", body="Forearm", point=[0.1, 0.0, 0.0], direction=[0.0, 0.0, 1.0], magnitude=20.0,
           start=0.05, duration=0.05, shape="half_sine")


@pytest.fixture(scope="module")
def cells(tmp_path_factory):
    character, traj = load_character(tiny_bvh(tmp_path_factory.mktemp("tiny") / "tiny.bvh"))
    from neuromotor.studies.simulate import prepare

    cfg = SimulationConfig(duration=0.5, perturbations=[HIT], reflex=ReflexSpec())
    rows = rs.stability_grid(cfg, [0.0, 1e6], [0.0, 0.1], setup=prepare(cfg, character, traj), chunk=4)
    return {(r["reflex_gain"], r["reflex_delay"]): r for r in rows}


def test_no_delayed_path_is_stable_and_a_huge_delayed_gain_is_flagged(cells):
    assert set(cells) == {(0.0, 0.0), (0.0, 0.1), (1e6, 0.0), (1e6, 0.1)}
    for d in (0.0, 0.1):
        ok = cells[(0.0, d)]
        assert ok["stability"] == "stable" and not ok["diverged"]
        assert 0.1 < ok["peak_deviation_deg"] < rs.STABLE_PEAK_DEG  # the push does deflect the arm
    # The delay does not matter at zero gain: the same controller, the same response.
    assert cells[(0.0, 0.0)]["peak_deviation_deg"] == pytest.approx(cells[(0.0, 0.1)]["peak_deviation_deg"], rel=1e-12)
    bad = cells[(1e6, 0.1)]
    assert bad["stability"] == "diverged" and bad["diverged"] and bad["diverged_step"] >= 0
    assert math.isnan(bad["peak_deviation_deg"])


def _row(g, d, status):
    peak = {"stable": 3.0, "large": 60.0, "diverged": math.nan}[status]
    return {"reflex_gain": g, "reflex_delay": d, "diverged": status == "diverged", "peak_deviation_deg": peak,
            "final_error_deg": 0.1 * peak, "recovery_time_s": 0.5 + g / 1000 if status == "stable" else math.nan}


SYNTHETIC = [_row(g, d, s) for g, d, s in [
    (0.0, 0.0, "stable"), (100.0, 0.0, "stable"), (1000.0, 0.0, "stable"),
    (0.0, 0.05, "stable"), (100.0, 0.05, "stable"), (1000.0, 0.05, "large"),
    (0.0, 0.1, "stable"), (100.0, 0.1, "diverged"), (1000.0, 0.1, "stable")]]


def test_classification_and_boundary():
    rows = rs.classified(SYNTHETIC)
    assert [r["stability"] for r in rows] == [
        "stable", "stable", "stable", "stable", "stable", "large", "stable", "diverged", "stable"]
    assert rs.classify(dict(SYNTHETIC[0], peak_deviation_deg=45.0)) == "large"  # the bound itself is not stable
    # An oscillation that has not decayed to half its peak by the window's end is not a recovery.
    assert rs.classify(dict(SYNTHETIC[0], final_error_deg=1.5)) == "sustained"
    assert rs.classify(dict(SYNTHETIC[0], final_error_deg=1.49)) == "stable"
    # The boundary is the first unstable gain per delay: a stable cell above it does not count.
    assert rs.stability_boundary(rows) == [
        {"delay_s": 0.0, "largest_stable_gain": 1000.0, "smallest_unstable_gain": None},
        {"delay_s": 0.05, "largest_stable_gain": 100.0, "smallest_unstable_gain": 1000.0},
        {"delay_s": 0.1, "largest_stable_gain": 0.0, "smallest_unstable_gain": 100.0}]


def test_stability_map_marks_unstable_cells_and_the_paper(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from neuromotor.viz import reflex_plots

    captured = {}
    orig = reflex_plots.save_png
    try:
        reflex_plots.save_png = lambda fig, path: captured.setdefault("fig", fig) and orig(fig, path)
        path = reflex_plots.plot_stability_map(rs.classified(SYNTHETIC), tmp_path / "map.png",
                                               **rs.map_options(SimulationConfig()))
    finally:
        reflex_plots.save_png = orig
    ax = captured["fig"].axes[0]
    marks = {ln.get_marker(): ln.get_xydata().tolist() for ln in ax.lines if ln.get_marker() not in ("None", "")}
    assert marks["x"] == [[1.0, 2.0]] and marks["^"] == [[2.0, 1.0]]  # (gain column, delay row)
    assert marks["*"] == [[0.0, 0.0]]  # the paper: no delayed path, no delay
    # Boundary segments: between (1000, 50 ms) and its stable neighbours, and around (100, 100 ms).
    edges = [ln for ln in ax.lines if ln.get_marker() in ("None", "") and ln.get_linewidth() > 2]
    assert len(edges) == 6
    assert path.stat().st_size > 5000
    plt.close("all")


def test_path_configs_switch_the_delayed_paths():
    cfg = SimulationConfig(reflex=ReflexSpec(gain=120.0, long_latency_gain=40.0))
    paths = rs.path_configs(cfg)
    assert list(paths) == list(rs.PATH_NAMES)
    none, spinal, both = paths.values()
    assert none.reflex is None
    assert (spinal.reflex.gain, spinal.reflex.long_latency_gain) == (120.0, 0.0)
    assert both.reflex == cfg.reflex
    assert all((c.ks, c.kd, c.perturbations) == (cfg.ks, cfg.kd, cfg.perturbations) for c in paths.values())
