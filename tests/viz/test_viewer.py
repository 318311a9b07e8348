"""The interactive viewer (``neuromotor view``, ``neuromotor.viz.show``): the page's data in the
Y-up frame, and the page itself in a real browser (Debian's headless Chromium, WebGL through
SwiftShader): it loads with no script error and fetches nothing, and screenshots before and after
the hit show the character and differ."""

from __future__ import annotations

import html
import json
import os
import pathlib
import re
import shutil
import subprocess

import imageio.v3 as iio
import numpy as np
import pytest
from test_render import HIT_START, Y_TO_Z, rotate_run, synthetic_run

from neuromotor.cli import main
from neuromotor.io.runfile import read_run
from neuromotor.viz import show
from neuromotor.viz.geometry import quat_matrices
from neuromotor.viz.html import deviation_deg, viewer_data, viewer_html, write_viewer, yup_order
from neuromotor.viz.scene import Scene

CHROMIUM = os.environ.get("NEUROMOTOR_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
WINDOW = (900, 650)
T_BEFORE, T_AFTER = 0.2, HIT_START + 0.15   # before the hit; at the synthetic lean's peak


def _zup_run(with_bodies=True, with_ball=True) -> dict:
    """The synthetic run of test_render turned Z-up (so the page must permute the axes)."""
    d = rotate_run(synthetic_run(with_bodies=with_bodies, with_ball=with_ball), Y_TO_Z)
    d["up_axis"] = np.asarray(2)
    d["source_clip"] = np.asarray("synthetic.bvh")
    return d


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("viewer") / "run.npz"
    np.savez(path, **_zup_run())
    return path


def _unpack(a) -> np.ndarray:
    import base64

    return np.frombuffer(base64.b64decode(a["b64"]), dtype=a["dtype"]).reshape(a["shape"])


# ------------------------------------------------------------------ the page's data (no browser)

def test_page_data_is_y_up_whatever_the_up_axis(run_file):
    """The Z-up run's page data equals the Y-up run's turned about the vertical: the same heights
    (Y), and world vertices (pose applied to the body-frame shapes) that match the run's own."""
    zup = viewer_data(read_run(run_file))
    yup = viewer_data(synthetic_run(with_bodies=True, with_ball=True))
    for part, key in (("shapes", "pos"), ("shapes", "pos_u"), ("capsules", "points"), ("ball", "pos")):
        np.testing.assert_allclose(_unpack(zup[part][key])[..., 1], _unpack(yup[part][key])[..., 1], atol=1e-6)
    assert zup["view"]["grid"]["center"][1] == pytest.approx(yup["view"]["grid"]["center"][1])
    # Pose x body-frame vertex in the page's frame = the run's world vertex, permuted.
    d = read_run(run_file)
    scene, order = Scene(d), yup_order(2)
    s = zup["shapes"]
    verts, ranges = _unpack(s["vertices"]), s["ranges"]
    pos, q = _unpack(s["pos"]), _unpack(s["quat"])
    k = int(np.searchsorted(scene.time, T_AFTER))
    R = quat_matrices(np.concatenate([q[k][:, 3:], q[k][:, :3]], axis=-1))   # x y z w -> w x y z
    page = np.concatenate([pos[k, b] + verts[v0:v0 + n] @ R[b].T for b, (v0, n, _, _) in enumerate(ranges)])
    world = np.concatenate([scene.shape_points(k, "perturbed")[d["shape_body"] == b] for b in range(len(ranges))])
    np.testing.assert_allclose(page, world[:, order], atol=1e-5)
    # Faces index their own body's vertices only.
    index = _unpack(s["index"])
    for v0, n, i0, ni in ranges:
        assert ni > 0 and index[i0:i0 + ni].max() < n


def test_deviation_curve_is_the_rms_angle_difference(run_file):
    """theta - theta_unperturbed = lean * w_i (test_render's synthetic run): the curve is
    |lean| * sqrt(mean w_i^2) in degrees, and wraps angles (a whole turn is no deviation)."""
    d = synthetic_run()
    t = d["time"]
    s = np.clip((t - HIT_START) / 0.15, 0, None)
    lean = 0.45 * s * np.exp(1 - s)
    w = np.linspace(1.0, 0.1, d["theta"].shape[1])
    expected = np.degrees(lean * np.sqrt(np.mean(w ** 2)))
    np.testing.assert_allclose(_unpack(viewer_data(d)["deviation"]), expected, atol=1e-4)
    turned = deviation_deg(d["theta"] + 2 * np.pi, d["theta_unperturbed"])
    np.testing.assert_allclose(turned, expected, atol=1e-9)


def test_force_arrow_follows_the_hit(run_file):
    """Drawn exactly while |F| exceeds 1% of its peak, |F| / 500 N per m long, pointing along F."""
    d = read_run(run_file)
    f = viewer_data(d)["force"]
    on, tail, tip = _unpack(f["on"]).astype(bool), _unpack(f["tail"]), _unpack(f["tip"])
    mag = np.linalg.norm(d["force_vector"], axis=1)
    np.testing.assert_array_equal(on, mag > 0.01 * mag.max())
    k = int(np.argmax(mag))
    order = yup_order(2)
    np.testing.assert_allclose(tip[k] - tail[k], d["force_vector"][k][order] / 500.0, atol=1e-5)
    assert f["label"] == "300 N"


# A URL where a browser would load it: an attribute, CSS url()/@import, an import or fetch().
FETCHABLE = re.compile(r"""(?:\b(?:src|href|action|poster|data)\s*=\s*["']?|url\(\s*["']?|@import\s+["']?"""
                       r"""|\bimport\s*\(?\s*["']|\bfrom\s*["']|\bfetch\(\s*["'])\s*(?:https?:)?//""", re.IGNORECASE)


def test_page_is_self_contained(run_file):
    """One page: three.js and the data inlined, nothing to fetch (no http(s) URL in a src,
    href, CSS url() or import), and show() wraps the same page in an iframe's srcdoc."""
    page = viewer_html(run_file)
    assert page.startswith("<!DOCTYPE html>") and "@@" not in page.split('id="nm-data"')[0]
    for loads in ('<script src="https://cdn.example/three.js">', "import * as T from 'https://x/three.js';",
                  "@import url(//fonts.example/a.css);", 'fetch("http://x/data.json")'):
        assert FETCHABLE.search(loads), loads
    assert FETCHABLE.findall(page) == []
    assert 'type="importmap"' not in page   # the import map is made at run time from blob: URLs
    assert "REVISION = '187'" in page and "class OrbitControls" in page
    viewer = show(read_run(run_file))   # the dict read_run gives (no angles: no curve)
    srcdoc = re.fullmatch(r'<iframe srcdoc="(.*)" style=.*</iframe>', viewer._repr_html_(), re.DOTALL).group(1)
    assert html.unescape(srcdoc) == viewer.html


def test_metrics_that_are_not_numbers_become_null():
    """A window that ends before the recovery has recovery_time_s NaN: the page's JSON holds null
    (the browser's JSON.parse rejects NaN, and the page would not start)."""
    d = synthetic_run()
    d["metrics_json"] = np.asarray(json.dumps({"peak_deviation_deg": 1.5, "recovery_time_s": float("nan")}))
    page = viewer_html(d)
    data = re.search(r'<script type="application/json" id="nm-data">(.*?)</script>', page, re.DOTALL).group(1)
    strict = json.loads(data, parse_constant=lambda c: pytest.fail(f"{c} in the page's JSON"))
    assert strict["meta"]["metrics"] == {"peak_deviation_deg": 1.5, "recovery_time_s": None}


def test_vendored_three_is_the_npm_package():
    """vendor/ holds unmodified copies of the pinned npm package's files (package.json)."""
    three = pathlib.Path(__file__).resolve().parents[2] / "node_modules" / "three"
    if not three.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"{three} missing: run npm ci (.ci/install)")
        pytest.skip(f"{three} missing (npm ci installs it)")

    from neuromotor.viz.html import THREE_VERSION, VENDOR

    assert json.loads((three / "package.json").read_text())["version"] == THREE_VERSION
    for name, source in (("three.core.js", "build"), ("three.module.js", "build"), ("LICENSE", ""),
                         ("OrbitControls.js", "examples/jsm/controls")):
        assert (VENDOR / name).read_bytes() == (three / source / name).read_bytes(), name


# ------------------------------------------------------------------ the command line

def test_cli_view_writes_the_page(run_file, tmp_path, capsys):
    out = tmp_path / "run.html"
    assert main(["view", str(run_file), "-o", str(out)]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {out}"
    assert out.read_text(encoding="utf-8") == viewer_html(run_file)


@pytest.mark.parametrize("case", ["missing", "not-an-npz", "bad-extension"])
def test_cli_view_bad_input(case, run_file, tmp_path, capsys):
    """Exit status 2, one line naming the file; an existing output is left as it was."""
    out = tmp_path / ("run.png" if case == "bad-extension" else "run.html")
    out.write_text("keep")
    run = {"missing": tmp_path / "missing.npz", "bad-extension": run_file}.get(case)
    if case == "not-an-npz":
        run = tmp_path / "junk.npz"
        run.write_text("not a zip")
    assert main(["view", str(run), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("neuromotor view: error: ")
    assert (str(out) if case == "bad-extension" else str(run)) in err
    assert out.read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_cli_view_onto_its_input_is_refused(run_file, capsys):
    before = run_file.read_bytes()
    assert main(["view", str(run_file), "-o", str(run_file)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert run_file.read_bytes() == before


def test_write_viewer_missing_field_names_it(tmp_path):
    d = synthetic_run()
    del d["theta_unperturbed"]
    np.savez(tmp_path / "old.npz", **d)
    with pytest.raises(ValueError, match="theta_unperturbed"):
        write_viewer(tmp_path / "old.npz", tmp_path / "old.html")
    assert not (tmp_path / "old.html").exists()


# ------------------------------------------------------------------ the page in a browser

def _need_chromium():
    if CHROMIUM is None:
        message = "headless Chromium not found (Debian package chromium; .ci/install_system_deps.sh)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)


def _open(page: pathlib.Path, query: str, png: pathlib.Path | None, profile: pathlib.Path,
          budget_ms: int = 4000, window=WINDOW, webgl: bool = True) -> dict:
    """Load ``page?query`` in headless Chromium and let it run for ``budget_ms`` of virtual time:
    the DOM then (status, the page's own error box) and the console lines Chromium logged.
    ``webgl=False``: no GPU and no software GL (``--disable-software-rasterizer``; with
    ``--disable-gpu`` alone Chromium 13x still falls back to SwiftShader), so no WebGL."""
    gl = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"] if webgl else ["--disable-software-rasterizer"]
    cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", *gl,
           "--hide-scrollbars", "--no-first-run", f"--user-data-dir={profile}",
           "--enable-logging=stderr", "--v=0", f"--window-size={window[0]},{window[1]}",
           f"--virtual-time-budget={budget_ms}", "--dump-dom"]
    if png is not None:
        cmd.append(f"--screenshot={png}")
    out = subprocess.run(cmd + [page.resolve().as_uri() + "?" + query], capture_output=True, text=True,
                         timeout=180, cwd=profile, check=False)
    status = re.search(r'<div id="nm-status"([^>]*)>([^<]*)<', out.stdout)
    attrs = dict(re.findall(r'(data-[a-z]+)="([^"]*)"', status.group(1))) if status else {}
    errors = re.search(r'<pre id="nm-errors">(.*?)</pre>', out.stdout, re.DOTALL)
    # SwiftShader's "GPU stall due to ReadPixels" (the screenshot itself) is not the page's.
    console = [line for line in out.stderr.splitlines() if ":CONSOLE" in line and "GL Driver Message" not in line]
    return {"status": status.group(2) if status else None, "attrs": attrs, "console": console,
            "errors": html.unescape(errors.group(1)) if errors else "(no #nm-errors in the DOM)",
            "dom": out.stdout}


@pytest.fixture(scope="module")
def browser_shots(run_file, tmp_path_factory):
    """The page at a time before the hit and one after it: (parsed DOM, screenshot) each."""
    _need_chromium()
    folder = tmp_path_factory.mktemp("browser")
    page = write_viewer(run_file, folder / "run.html")
    shots = {}
    for name, t in (("before", T_BEFORE), ("after", T_AFTER)):
        png = folder / f"{name}.png"
        shots[name] = (_open(page, f"t={t}", png, folder), iio.imread(png)[..., :3].astype(float))
    return shots


CHART_PX, CONTROLS_MAX_PX = 150, 80   # the curve's height (viewer_template.html); two rows of controls


def _view(shot):
    """The 3-D view: the screenshot above the controls and the curve."""
    return shot[1][:WINDOW[1] - CHART_PX - CONTROLS_MAX_PX]


def _character(img) -> np.ndarray:
    """Pixels of the perturbed figure's orange (lit or shaded)."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 70) & (r > 1.4 * g) & (g > 1.25 * b)


def test_page_loads_in_chromium_without_errors(browser_shots, run_file):
    """No script error, no console.error, nothing fetched; WebGL on; ?t= picked the sample."""
    time = read_run(run_file)["time"]
    for name, t in (("before", T_BEFORE), ("after", T_AFTER)):
        dom, _ = browser_shots[name]
        assert dom["errors"] == "", dom["errors"]
        assert dom["console"] == []
        assert dom["status"] == "ready" and dom["attrs"]["data-webgl"] == "1"
        assert int(dom["attrs"]["data-index"]) == int(np.argmin(np.abs(time - t)))


def test_screenshots_show_the_character_and_change_after_the_hit(browser_shots):
    before, after = _view(browser_shots["before"]), _view(browser_shots["after"])
    assert before.shape == after.shape and before.shape[0] > 300
    for img in (before, after):
        assert img.std() > 10.0                      # not blank
        assert _character(img).sum() > 1500          # the orange figure is drawn
    changed = np.abs(before - after).max(axis=-1) > 40
    assert changed.mean() > 0.01                     # the lean (and the ball) moved
    a, b = _character(before), _character(after)
    assert (a & b).sum() / (a | b).sum() < 0.85      # the figure itself moved


def test_run_without_shapes_draws_capsules_and_plays_in_chromium(tmp_path):
    """An older RUN.npz without body shapes: every bone a capsule; the page loads and, without
    ?t=, plays at the speed asked for: 0.25 x the 1.5 s of virtual time it runs for = 0.375 s."""
    _need_chromium()
    d = _zup_run(with_bodies=False, with_ball=False)
    data = viewer_data(d)
    assert data["shapes"] is None and data["ball"] is None
    assert _unpack(data["capsules"]["edges"]).shape == d["skeleton_edges"].shape
    np.savez(tmp_path / "old.npz", **d)
    page = write_viewer(tmp_path / "old.npz", tmp_path / "old.html")
    dom = _open(page, "speed=0.25", None, tmp_path, budget_ms=1500, window=(480, 360))
    assert dom["errors"] == "", dom["errors"]
    assert dom["console"] == [] and dom["status"] == "ready"
    played = float(dom["attrs"]["data-time"]) - float(d["time"][0])
    assert 0.75 * 0.375 <= played <= 0.375 + 0.01


def test_page_without_webgl_says_so_and_still_draws_the_curve(run_file, tmp_path):
    """Chromium with no GPU and no software GL: one line where the picture would be, no script
    error, the time of ?t= in the timeline, and the deviation curve (orange) with its red cursor."""
    _need_chromium()
    page = write_viewer(run_file, tmp_path / "run.html")
    png = tmp_path / "nogl.png"
    dom = _open(page, f"t={T_AFTER}", png, tmp_path, webgl=False)
    assert dom["errors"] == "", dom["errors"]
    assert dom["console"] == [] and dom["status"] == "ready" and dom["attrs"]["data-webgl"] == "0"
    note = re.search(r'<div id="nm-no-webgl"([^>]*)>([^<]*)<', dom["dom"])
    assert note and "hidden" not in note.group(1) and "no WebGL" in note.group(2)
    time = read_run(run_file)["time"]
    k = int(np.argmin(np.abs(time - T_AFTER)))
    assert int(dom["attrs"]["data-index"]) == k
    assert f"t = {time[k]:.3f} s" in dom["dom"]
    img = iio.imread(png)[..., :3].astype(float)
    chart = img[WINDOW[1] - CHART_PX:]
    r, g, b = chart[..., 0], chart[..., 1], chart[..., 2]
    curve = (np.abs(r - 230) < 40) & (np.abs(g - 115) < 40) & (np.abs(b - 51) < 40)
    cursor = (r > 150) & (g < 60) & (b < 60)
    assert curve.sum() > 200 and cursor.sum() > 50
    assert _character(_view((dom, img))).sum() == 0   # no figure drawn


def test_the_balance_assist_is_drawn_and_named_in_chromium(tmp_path):
    """A run with the balance assist on (issue 38): its virtual force on the pelvis is an arrow
    |F| / 500 N per m long in the page's Y-up frame, and the metrics line names it as help, not
    physics, with its impulse."""
    _need_chromium()
    d = _zup_run(with_bodies=False, with_ball=False)
    T = d["time"].shape[0]
    point = np.tile([0.1, 0.2, 0.9], (T, 1))                  # Z up, as the run
    force = np.zeros((T, 3))
    force[:, 0] = 60.0 * np.sin(np.linspace(0.0, np.pi, T))   # along x, growing then shrinking
    d.update(assist_force=force, assist_point=point,
             metrics_json=np.asarray('{"peak_deviation_deg": 3.0, "assist_impulse_Ns": 12.5, "assist_impulse_pct": 0.75}'))
    data = viewer_data(d)
    tail, tip = _unpack(data["assist"]["tail"]), _unpack(data["assist"]["tip"])
    order = [1, 2, 0]  # Z up to the page's Y up: a cyclic permutation (html.yup_order)
    np.testing.assert_allclose(tail, point[:, order], atol=1e-6)
    np.testing.assert_allclose(tip - tail, force[:, order] / 500.0, atol=1e-6)
    np.savez(tmp_path / "assist.npz", **d)
    page = write_viewer(tmp_path / "assist.npz", tmp_path / "assist.html")
    dom = _open(page, "t=0.5", None, tmp_path, budget_ms=1500, window=(480, 360))
    assert dom["errors"] == "", dom["errors"]
    assert dom["console"] == [] and dom["status"] == "ready"
    line = re.search(r'<div id="nm-metrics">([^<]*)<', dom["dom"]).group(1)
    assert "assist (not physics, purple arrow) 12.5 N s = 0.75 % BW" in html.unescape(line), line


def test_a_platform_carries_the_pages_ground_and_plays_in_chromium(tmp_path):
    """A free root on a moving platform (issue 38): the page gets the platform's displacement per
    sample in its Y-up frame (its ground rides on it) and plays without errors; the same shift on
    a driven root's file (a sled moves the root, not the ground) gives the page none."""
    import json

    _need_chromium()
    d = _zup_run(with_bodies=False, with_ball=False)
    T = d["time"].shape[0]
    shift = np.zeros((T, 3))
    shift[:, 0] = -0.3 * np.linspace(0.0, 1.0, T) ** 2  # backward along x, Z up
    shift[:, 2] = 0.05 * np.sin(np.linspace(0.0, np.pi, T))  # and up and down
    d.update(base_offset=shift, ground_height=np.asarray(0.0),
             provenance_json=np.asarray(json.dumps({"root": "free"})))
    data = viewer_data(d)
    np.testing.assert_allclose(_unpack(data["platform"]), shift[:, [1, 2, 0]], atol=1e-6)
    assert viewer_data({**d, "provenance_json": np.asarray(json.dumps({"root": "driven"}))})["platform"] is None
    np.savez(tmp_path / "platform.npz", **d)
    page = write_viewer(tmp_path / "platform.npz", tmp_path / "platform.html")
    dom = _open(page, "t=0.5", None, tmp_path, budget_ms=1500, window=(480, 360))
    assert dom["errors"] == "", dom["errors"]
    assert dom["console"] == [] and dom["status"] == "ready"
