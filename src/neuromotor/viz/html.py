"""The interactive viewer: one self-contained HTML page of a run, in a browser or in Jupyter.

    write_viewer("run.npz", "run.html")   # what `neuromotor view run.npz -o run.html` does
    show("run.npz")                       # the same page inline in a notebook (an iframe)

The page holds everything it needs, so it opens offline: three.js 0.187.0 (vendored from its
npm package, MIT licence, in ``neuromotor/viz/vendor/``), the page's own script
(``viewer.js``) and the run's arrays as base64 float32 in a JSON block. The modules are handed
to the browser through an import map of ``blob:`` URLs made from inline ``<script
type="text/plain">`` blocks (see ``viewer_template.html``).

What the page shows, all in three.js's Y-up frame whatever the clip's ``up_axis`` (the world
axes are permuted cyclically so that up becomes Y: a proper rotation, positions and the
quaternions' vector parts alike):

* the perturbed character (each body's convex polyhedron posed by ``body_pos``/``body_quat``,
  bones that carry no body as thin capsules; without shapes, every bone as a capsule of radius
  ``skeleton_radii``) and the unperturbed one as a translucent ghost;
* the force arrow as in the filmstrip (:meth:`neuromotor.viz.scene.Scene.arrow`: tip 1 cm
  outside the body, ``|F| / FORCE_SCALE_N_PER_M`` long, shown while ``|F|`` exceeds 1% of its
  peak), the ball when the run has one, a ground grid at the lowest point of the run;
* a time slider, play/pause at speed 1, 0.5, 0.25 or 0.1, orbit/zoom, a checkbox per layer, and
  under it the deviation d(t) in degrees that the run's metrics came from (the file's
  ``deviation``: by default the RMS over joints of each joint's geodesic rotation angle, see
  :mod:`neuromotor.studies.metrics`; files without it: the Euler-DOF form
  ``sqrt(mean_i wrap(theta_i - theta_unperturbed_i)^2)``) with a cursor at the current time.

``?t=SECONDS`` in the page's URL (or ``window.neuromotorSetTime(t)``) shows that instant,
paused; without it the page plays from the start (``?speed=0.25``: slowed). Script errors are
shown in the page (``#nm-errors``) as well as in the console.
"""

from __future__ import annotations

import base64
import html
import json
import pathlib
import re
from collections.abc import Mapping

import numpy as np

from neuromotor.atomic import atomic_path
from neuromotor.io.runfile import DRAW_FIELDS, PLOT_FIELDS, check_run, json_field, source_clip
from neuromotor.viz.data import RenderError, load_run
from neuromotor.viz.scene import Scene
from neuromotor.viz.style import (
    COLOR_ASSIST,
    COLOR_BALL,
    COLOR_FORCE,
    COLOR_GHOST,
    COLOR_PERTURBED,
    FORCE_SCALE_N_PER_M,
    GROUND_TILE_M,
)

THREE_VERSION = "0.187.0"
HERE = pathlib.Path(__file__).parent
VENDOR = HERE / "vendor"
TEMPLATE = HERE / "viewer_template.html"
APP = HERE / "viewer.js"
VIEW_FIELDS = tuple(dict.fromkeys(DRAW_FIELDS + PLOT_FIELDS))
HTML_EXTENSIONS = (".html", ".htm")
IFRAME_HEIGHT_PX = 640

# Inline block id -> (file, the relative import to rewrite to a bare name the import map knows).
_MODULES = {
    "nm-src-three-core": ("three.core.js", None),
    "nm-src-three": ("three.module.js", ("'./three.core.js'", "'three-core'")),
    "nm-src-orbit": ("OrbitControls.js", None),
}


# ----------------------------------------------------------------------------------------------
# The run's arrays, in the page's frame
# ----------------------------------------------------------------------------------------------


def yup_order(up_axis: int) -> list[int]:
    """Index order taking world axes to three.js's (X, Y, Z) with ``up_axis`` as Y: the cyclic
    permutation ``new[i] = old[(i + up_axis - 1) % 3]`` (a rotation, so handedness is kept)."""
    return [(i + int(up_axis) - 1) % 3 for i in range(3)]


def xyzw(q_wxyz, order) -> np.ndarray:
    """Quaternions (..., 4) w x y z in world axes -> x y z w in the permuted axes: rotating the
    frame by a permutation P maps R to P R P^T, whose quaternion has vector part P v."""
    q = np.asarray(q_wxyz, float)
    return np.concatenate([q[..., 1:][..., order], q[..., :1]], axis=-1)


def deviation_deg(theta, theta_unperturbed) -> np.ndarray:
    """(T,) RMS over DOFs of the wrapped angle difference, degrees (as in
    :func:`neuromotor.studies.metrics.deviation`)."""
    diff = np.asarray(theta, float) - np.asarray(theta_unperturbed, float)
    diff = np.arctan2(np.sin(diff), np.cos(diff))
    return np.degrees(np.sqrt(np.mean(diff**2, axis=-1)))


def _packed(a, dtype="float32") -> dict:
    """An array for the page: dtype, shape and little-endian bytes in base64."""
    a = np.ascontiguousarray(np.asarray(a), dtype=np.dtype(dtype).newbyteorder("<"))
    return {"dtype": np.dtype(dtype).name, "shape": list(a.shape), "b64": base64.b64encode(a.tobytes()).decode()}


def _shape_part(d, order) -> dict:
    """Body polyhedra split per body (vertices in the body frame, faces indexing them) and
    both figures' poses."""
    v = np.asarray(d["shape_vertices"], float)[:, order]
    f = np.asarray(d["shape_faces"], int)
    owner = np.asarray(d["shape_body"], int)
    B = d["body_pos"].shape[1]
    verts: list[np.ndarray] = []
    index: list[np.ndarray] = []
    ranges: list[list[int]] = []
    for b in range(B):
        ids = np.flatnonzero(owner == b)
        faces = f[(owner[f] == b).all(axis=1)]  # a face spanning bodies has no one frame: left out
        local = np.full(len(v), -1)
        local[ids] = np.arange(len(ids))
        ranges.append([sum(len(x) for x in verts), len(ids), sum(len(x) for x in index), faces.size])
        verts.append(v[ids])
        index.append(local[faces].ravel())
    return {
        "vertices": _packed(np.concatenate(verts)),
        "index": _packed(np.concatenate(index), "uint32"),
        "ranges": ranges,
        "pos": _packed(d["body_pos"][..., order]),
        "quat": _packed(xyzw(d["body_quat"], order)),
        "pos_u": _packed(d["body_pos_unperturbed"][..., order]),
        "quat_u": _packed(xyzw(d["body_quat_unperturbed"], order)),
    }


def _capsule_part(scene: Scene, order) -> dict | None:
    """Bones drawn as capsules (detail bones beside the shapes, or every bone without them):
    only the points they use, both figures."""
    edges, radii = scene.capsule_edges, scene.capsule_radii
    if len(edges) == 0:
        return None
    used, local = np.unique(edges, return_inverse=True)
    return {
        "edges": _packed(local.reshape(-1, 2), "uint32"),
        "radii": _packed(radii),
        "points": _packed(scene.P[:, used][..., order]),
        "points_u": _packed(scene.U[:, used][..., order]),
    }


def _force_part(scene: Scene, order) -> dict:
    """The arrow's tail and tip per sample (zero where it is not drawn), and its label."""
    T = len(scene.time)
    tail, tip = np.zeros((T, 3)), np.zeros((T, 3))
    for k in np.flatnonzero(scene.force_on):
        tail[k], tip[k] = scene.arrow(int(k))
    on = np.flatnonzero(scene.force_on)
    label = scene.force_label(int(on[np.argmax(scene.fmag[on])])) if len(on) else ""
    return {
        "tail": _packed(tail[:, order]),
        "tip": _packed(tip[:, order]),
        "on": _packed(scene.force_on, "uint8"),
        "label": label,
    }


def _assist_part(d, order) -> dict | None:
    """The balance assist's virtual force on the pelvis (when the run had it on): an arrow from
    the pelvis's COM along the force, ``|F| / FORCE_SCALE_N_PER_M`` long, at every sample, so
    that help is never taken for physics."""
    if "assist_force" not in d:
        return None
    force, point = np.asarray(d["assist_force"], float), np.asarray(d["assist_point"], float)
    return {
        "tail": _packed(point[:, order]),
        "tip": _packed((point + force / FORCE_SCALE_N_PER_M)[:, order]),
        "peak_N": float(np.linalg.norm(force, axis=1).max()),
    }


def _framing(scene: Scene, order) -> dict:
    """Camera (three-quarter front view as in the filmstrip, perspective) and ground grid."""
    pts = np.concatenate([scene.P.reshape(-1, 3), scene.U.reshape(-1, 3)])[:, order]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    target = 0.5 * (lo + hi)
    size = float(max(hi[1] - lo[1], 0.6 * np.linalg.norm((hi - lo)[[0, 2]]), 0.5))
    fov = 35.0
    distance = 0.62 * size / np.tan(np.radians(fov / 2))
    span = float(np.linalg.norm((hi - lo)[[0, 2]])) + 2 * size
    tiles = 2 * int(np.ceil(span / (2 * GROUND_TILE_M)))
    centre = np.round(target / GROUND_TILE_M) * GROUND_TILE_M
    return {
        "target": target.tolist(),
        "position": (target + distance * scene.view[order]).tolist(),
        "fov": fov,
        "grid": {
            "center": [float(centre[0]), scene.ground, float(centre[2])],
            "size": tiles * GROUND_TILE_M,
            "divisions": tiles,
        },
    }


def _meta(d, scene: Scene) -> dict:
    """Title, the hits' time windows (shaded under the curve) and the metrics shown as text."""
    clip = pathlib.Path(str(d["source_clip"])).name if "source_clip" in d else ""
    # Each stretch of samples where something hits (a force or the ball's contact), as [t0, t1].
    on = np.concatenate([[0], scene.hit_on.astype(int), [0]])
    starts, ends = np.flatnonzero(np.diff(on) == 1), np.flatnonzero(np.diff(on) == -1) - 1
    t = scene.time
    return {
        "title": f"neuromotor run{': ' + clip if clip else ''}",
        "clip": clip,
        "up_axis": scene.up_axis,
        "hits": [[float(t[a]), float(t[b])] for a, b in zip(starts, ends)],
        "metrics": _strict_json(json_field(d, "metrics_json")),
        "colors": {
            "perturbed": COLOR_PERTURBED,
            "ghost": COLOR_GHOST,
            "force": COLOR_FORCE,
            "ball": COLOR_BALL,
            "assist": COLOR_ASSIST,
        },
    }


def _strict_json(value):
    """NaN and infinities (a run that never recovers has recovery_time_s NaN) as null: the
    browser's JSON.parse rejects them and the page would not start."""
    if isinstance(value, dict):
        return {k: _strict_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_strict_json(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def viewer_data(d: Mapping[str, np.ndarray]) -> dict:
    """Everything the page draws, from a run's arrays ``d`` (checked): JSON-ready, numbers as
    base64 float32 (``time`` float64), positions in the Y-up frame."""
    scene = Scene(d)
    order = yup_order(scene.up_axis)
    out = {
        "meta": _meta(d, scene),
        "time": _packed(scene.time, "float64"),
        "view": _framing(scene, order),
        "shapes": _shape_part(d, order) if scene.has_shapes else None,
        "capsules": _capsule_part(scene, order),
        "force": _force_part(scene, order),
        "deviation": None,
        "ball": None,
        "assist": _assist_part(d, order),
        "tilt": None,
        "platform": None,
    }
    if "ground_turn" in d:  # a tilted ground: the grid turns about the pivot with it, sample by sample
        out["tilt"] = {
            "pivot": np.asarray(d["ground_pivot"], float)[order].tolist(),
            "quat": _packed(xyzw(d["ground_turn"], order)),
        }
    if scene.ground_shift is not None:  # a platform carries the ground (and the tilt's pivot) along
        out["platform"] = _packed(scene.ground_shift[:, order])
    if "deviation" in d:  # the curve the run's metrics came from ([sim] metric)
        out["deviation"] = _packed(d["deviation"])
    elif "theta" in d and "theta_unperturbed" in d:  # older files: the Euler-DOF form
        out["deviation"] = _packed(deviation_deg(d["theta"], d["theta_unperturbed"]))
    if "ball_pos" in d:
        out["ball"] = {"pos": _packed(np.asarray(d["ball_pos"])[:, order]), "radius": float(d["ball_radius"])}
    return out


# ----------------------------------------------------------------------------------------------
# The page
# ----------------------------------------------------------------------------------------------


def _inline_text(name: str, text: str) -> str:
    """Text safe inside a raw-text ``<script>`` element (no end tag, no comment opener)."""
    if re.search(r"</script|<!--", text, re.IGNORECASE):
        raise RuntimeError(f"{name}: cannot be inlined in a <script> element (contains '</script' or '<!--')")
    return text


def _modules() -> dict[str, str]:
    """The vendored three.js modules and the page's script, keyed by their inline block's id."""
    out = {}
    for block, (name, rewrite) in _MODULES.items():
        text = (VENDOR / name).read_text(encoding="utf-8")
        if rewrite is not None:
            old, new = rewrite
            if old not in text:
                raise RuntimeError(f"{VENDOR / name}: expected an import of {old}")
            text = text.replace(old, new)
        out[block] = _inline_text(name, text)
    out["nm-src-app"] = _inline_text(APP.name, APP.read_text(encoding="utf-8"))
    return out


def _run_arrays(run) -> tuple[str, dict]:
    """(label, checked arrays) of a RUN.npz path or of the dict :func:`read_run` returns."""
    if isinstance(run, Mapping):
        d = {k: np.asarray(v) for k, v in run.items()}
        missing = [f for f in DRAW_FIELDS if f not in d]
        if missing:
            raise RenderError(f"run: missing array(s) {', '.join(missing)}")
        check_run("run", d, RenderError)
        return "run", d
    d = load_run(run, VIEW_FIELDS)
    clip = source_clip(run)  # for the title only
    if clip is not None:
        d["source_clip"] = np.asarray(clip)
    return str(run), d


def viewer_html(run) -> str:
    """The viewer page of ``run`` (a RUN.npz path, or the dict of arrays from
    :func:`neuromotor.io.runfile.read_run`) as one self-contained HTML string."""
    _, d = _run_arrays(run)
    data = viewer_data(d)
    # '<' escaped so that no string in the JSON can end the <script> element holding it.
    parts = {
        "DATA": json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c"),
        "TITLE": html.escape(data["meta"]["title"]),
        "THREE_VERSION": THREE_VERSION,
        **{block.upper().replace("-", "_"): text for block, text in _modules().items()},
    }
    template = TEMPLATE.read_text(encoding="utf-8")
    # One pass, so that nothing inserted is scanned for markers again.
    return re.sub(r"@@([A-Z_]+)@@", lambda m: parts[m.group(1)], template)


def write_viewer(run, out_html) -> pathlib.Path:
    """Write the viewer page of ``run`` to ``out_html`` (``.html``/``.htm``), atomically: on any
    error an existing file is left as it was."""
    out = pathlib.Path(out_html)
    if out.suffix.lower() not in HTML_EXTENSIONS:
        raise RenderError(f"{out}: unknown output extension {out.suffix!r}; the viewer is written as .html")
    page = viewer_html(run)
    with atomic_path(out) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return out


class Viewer:
    """The viewer page of a run for Jupyter: displays as an iframe whose ``srcdoc`` is the page."""

    def __init__(self, page: str, height: int = IFRAME_HEIGHT_PX):
        self.html, self.height = page, int(height)

    def _repr_html_(self) -> str:
        return (
            f'<iframe srcdoc="{html.escape(self.html, quote=True)}" style="width:100%;'
            f'height:{self.height}px;border:1px solid #ddd" title="neuromotor viewer"></iframe>'
        )

    def save(self, path) -> pathlib.Path:
        """Write the page to ``path`` (atomically)."""
        with atomic_path(path) as tmp:
            tmp.write_text(self.html, encoding="utf-8")
        return pathlib.Path(path)


def show(run, height: int = IFRAME_HEIGHT_PX) -> Viewer:
    """The viewer of ``run`` (a RUN.npz path or the dict from :func:`read_run`) inline in a
    notebook: ``neuromotor.viz.show("run.npz")`` as the last line of a cell."""
    return Viewer(viewer_html(run), height)
