"""RUN.npz: the one reader and the one writer of a simulated run's file.

The file is a plain NumPy ``.npz`` (no pickles). Its fields, by group:

* always (``INFO_FIELDS``): ``time`` (T,) strictly increasing seconds and ``theta`` (T, n)
  joint angles (rad, continuous in time);
* drawing (``DRAW_FIELDS``): ``skeleton_points`` and ``skeleton_points_unperturbed`` (T, P>=2, 3),
  ``skeleton_edges`` (E>=1, 2) integer parent -> child point pairs, ``skeleton_radii`` (E,) > 0,
  ``force_origin`` and ``force_vector`` (T, 3);
* plots (``PLOT_FIELDS``): ``dof_names`` (n,), ``theta``, ``theta_unperturbed``,
  ``theta_desired`` (T, n), ``force_vector``;
* BVH export (``EXPORT_FIELDS``): ``dof_names``, ``source_clip`` and ``source_units`` (strings),
  ``up_axis`` (scalar 0, 1 or 2);
* optional (``OPTIONAL_FIELDS``, read whenever present): ``up_axis``, ``facing`` (3,) the
  horizontal facing direction, ``skeleton_edge_body`` (E,) the body carrying each bone (-1 for
  none), ``metrics_json`` and ``provenance_json`` (JSON strings), the ball's ``ball_pos`` (T, 3)
  and ``ball_radius`` (scalar > 0), which come together, ``contact_force`` (T, C, 3) and
  ``body_names`` (B,), ``deviation`` (T,) the deviation d(t) in degrees that the metrics were
  computed from, ``base_offset`` (T, 3) the base motion's displacement of the driven root
  (with a free root on a ground: of the ground, a platform) (world, m), ``ground_height``
  (scalar, m) a ground's level height along up, ``ground_turn`` (T, 4) and ``ground_pivot`` (3,)
  a tilted ground's orientation (unit quaternions w, x, y, z, world) and the point it turns about
  (world, m), which come with ``ground_height``, and
  ``deviation_metric`` its definition (a string: ``geodesic`` or ``euler``, see
  :mod:`neuromotor.studies.metrics`; files without them are drawn with the Euler form),
  ``clip_still`` (scalar, s) the clip time of the pose a ``[sim] still`` run holds (absent: the
  clip plays, ``time`` is clip time);
* the capture's residuals with the ground (``RESIDUAL_FIELDS``, all or none; issue 38,
  :mod:`neuromotor.studies.residuals`): ``residual_force`` and ``residual_moment`` (T, 3) the
  root's wrench the ground reaction forces leave (N, N m, world), the moment about
  ``residual_point`` (T, 3) the whole body's COM; per contact body ``grf_body`` (K,) its index,
  ``grf_force`` (T, K, 3) its ground reaction force (N), ``grf_point`` (T, K, 3) the centre of
  pressure on the floor and ``grf_torque`` (T, K, 3) the free torque about it (N m);
  ``contact_points`` (T,) the touching vertices; ``residuals_json`` the RMS and peak figures;
* the balance assist (issue 38; only when ``[balance] assist`` is on, both or neither):
  ``assist_force`` (T, 3) the virtual force on the pelvis (N, world: help, not physics) and
  ``assist_point`` (T, 3) the pelvis's COM where it acts (m);
* body shapes (``SHAPE_FIELDS``, all or none): ``shape_vertices`` (V, 3) in the body frame less
  the body's COM, ``shape_faces`` (F, 3) and ``shape_body`` (V,) integer, with the poses
  ``body_pos`` (T, B, 3), ``body_quat`` (T, B, 4, w x y z) and their ``_unperturbed`` twins.

The simulation writes more (``perturbation_force``, ``kkt_residual``, the ball's contact
arrays, ...): :func:`write_run` stores whatever it is given, readers take what they ask for.
"""

from __future__ import annotations

import json
import pathlib
import zipfile
from collections.abc import Iterable, Mapping

import numpy as np

from neuromotor.atomic import atomic_path
from neuromotor.errors import UserError

INFO_FIELDS = ("time", "theta")
DRAW_FIELDS = (
    "time",
    "skeleton_points",
    "skeleton_points_unperturbed",
    "skeleton_edges",
    "skeleton_radii",
    "force_origin",
    "force_vector",
)
PLOT_FIELDS = ("time", "dof_names", "theta", "theta_unperturbed", "theta_desired", "force_vector")
EXPORT_FIELDS = ("time", "theta", "dof_names", "source_clip", "source_units", "up_axis")
OPTIONAL_FIELDS = (
    "up_axis",
    "ball_pos",
    "ball_radius",
    "metrics_json",
    "facing",
    "skeleton_edge_body",
    "contact_force",
    "provenance_json",
    "body_names",
    "deviation",
    "deviation_metric",
    "base_offset",
    "ground_turn",
    "ground_pivot",
    "ground_height",
    "clip_still",
    "assist_force",
    "assist_point",
    "residual_force",
    "residual_moment",
    "residual_point",
    "grf_force",
    "grf_point",
    "grf_torque",
    "grf_body",
    "contact_points",
    "residuals_json",
)
RESIDUAL_FIELDS = OPTIONAL_FIELDS[OPTIONAL_FIELDS.index("residual_force") :]
# The JSON strings read_run_info parses, by the key it returns them under.
JSON_FIELDS = {"provenance_json": "provenance", "metrics_json": "metrics", "residuals_json": "residuals"}
SHAPE_FIELDS = (
    "shape_vertices",
    "shape_faces",
    "shape_body",
    "body_pos",
    "body_quat",
    "body_pos_unperturbed",
    "body_quat_unperturbed",
)
POSE_FIELDS = ("body_pos", "body_quat", "body_pos_unperturbed", "body_quat_unperturbed")


class RunFileError(UserError):
    """A file that is not a readable, well-formed RUN.npz; the message names the file and field."""


# ----------------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------------


def save_npz_atomic(path, arrays: Mapping[str, np.ndarray]) -> pathlib.Path:
    """Write an .npz through a temporary file in the same folder, then rename."""
    path = pathlib.Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]  # numpy stubs: ** may not fill allow_pickle
    return path


def write_run(path, arrays: Mapping[str, np.ndarray], extra: Mapping[str, np.ndarray] | None = None) -> pathlib.Path:
    """Write a RUN.npz atomically: ``arrays`` (the contract above) plus ``extra`` arrays that a
    study adds (a ball's trajectory and contacts); an extra name may not replace a field."""
    extra = dict(extra or {})
    clash = sorted(set(extra) & set(arrays))
    if clash:
        raise ValueError(f"extra run arrays would replace field(s) {', '.join(clash)}")
    return save_npz_atomic(path, {**arrays, **extra})


# ----------------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------------


def _wanted_fields(path, names: set, fields: Iterable[str], error) -> set:
    """The arrays to read: ``fields`` (all must exist), the optional ones present, and the body
    shapes (all or none) when drawing."""
    fields = tuple(fields)
    missing = [f for f in fields if f not in names]
    if missing:
        raise error(f"{path}: missing array(s) {', '.join(missing)} (not a RUN.npz from `neuromotor simulate`?)")
    wanted = set(fields) | (set(OPTIONAL_FIELDS) & names)
    if "skeleton_points" in fields and "shape_vertices" in names:
        missing = [f for f in SHAPE_FIELDS if f not in names]
        if missing:
            raise error(
                f"{path}: has shape_vertices but lacks array(s) {', '.join(missing)} needed to draw the body shapes"
            )
        wanted |= set(SHAPE_FIELDS)
    return wanted


def _exists(path: pathlib.Path, error) -> None:
    if path.is_dir():
        raise error(f"{path}: is a directory, not a run file")
    if not path.is_file():
        raise error(f"{path}: no such run file")


def _unreadable(path: pathlib.Path, e: Exception) -> str:
    """Why a file is not a RUN.npz, in the user's terms (NumPy reads any non-zip file as a
    pickle and says so, which misleads for a config or a clip given by mistake)."""
    if not zipfile.is_zipfile(path):
        return f"{path}: not a RUN.npz (not an .npz archive; give the file `neuromotor simulate -o` wrote)"
    return f"{path}: cannot read as .npz: {e}"


def read_run(
    run_path, fields: Iterable[str] = DRAW_FIELDS, error: type[ValueError] = RunFileError, check: bool = True
) -> dict[str, np.ndarray]:
    """Read the arrays ``fields`` of a RUN.npz (each must be there) plus the optional fields
    present and, when ``fields`` include the skeleton, the body shapes (all or none); then
    :func:`check_run` them. Problems raise ``error`` naming the file and the field."""
    path = pathlib.Path(run_path)
    _exists(path, error)
    try:
        with np.load(path, allow_pickle=False) as npz:
            wanted = _wanted_fields(path, set(npz.files), fields, error)
            data = {k: np.asarray(npz[k]) for k in wanted}
    except error:
        raise
    except Exception as e:  # zipfile.BadZipFile, ValueError (pickled object arrays), OSError
        raise error(_unreadable(path, e)) from None
    if check:
        check_run(path, data, error)
    return data


def read_run_info(path) -> dict:
    """Provenance, metrics and array shapes of a RUN.npz; :class:`RunFileError` naming the file
    when it is not one (missing, unreadable, not an .npz, no ``time``/``theta``, malformed JSON)."""
    path = pathlib.Path(path)
    _exists(path, RunFileError)
    try:
        with np.load(path, allow_pickle=False) as data:
            shapes = {k: list(data[k].shape) for k in data.files}
            text = {k: str(data[k]) for k in JSON_FIELDS if k in data.files}
    except Exception as e:  # zip, pickle, truncation errors all mean the same to the user
        raise RunFileError(_unreadable(path, e)) from None
    _wanted_fields(path, set(shapes), INFO_FIELDS, RunFileError)
    out = {"file": str(path), **dict.fromkeys(JSON_FIELDS.values()), "arrays": shapes}
    for key, field in JSON_FIELDS.items():
        if key in text:
            try:
                out[field] = json.loads(text[key])
            except json.JSONDecodeError as e:
                raise RunFileError(f"{path}: {key} is not valid JSON ({e})") from None
    return out


def json_field(d: Mapping, key: str) -> dict | None:
    """A JSON object stored as a string array (``metrics_json``, ``provenance_json``), or None
    when absent, unreadable or not an object."""
    if key not in d:
        return None
    try:
        value = json.loads(str(d[key]))
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def source_clip(run_path) -> str | None:
    """The clip a RUN.npz was made from (``source_clip``), or None when it cannot be read."""
    try:
        with np.load(run_path, allow_pickle=False) as data:
            if "source_clip" in data.files:
                return str(data["source_clip"])
    except Exception:  # not a readable run: the command that reads it says so
        pass
    return None


# ----------------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------------


class _Checker:
    """Shape and value checks of one run's arrays; each failure names the file and the field."""

    def __init__(self, path, d, error):
        self.path, self.d, self.error = path, d, error

    def fail(self, field, msg):
        raise self.error(f"{self.path}: field '{field}' {msg}")

    def finite(self, field):
        if not np.all(np.isfinite(self.d[field])):
            self.fail(field, "contains non-finite values (did the simulation diverge?)")

    def shape(self, field, shape):
        if self.d[field].shape != shape:
            self.fail(field, f"must have shape {shape}, got {self.d[field].shape}")

    def time(self) -> int:
        t = self.d["time"]
        if t.ndim != 1 or t.shape[0] < 1:
            self.fail("time", f"must have shape (T,), got {t.shape}")
        if t.dtype.kind not in "fi":
            self.fail("time", f"must be numeric, got dtype {t.dtype}")
        self.finite("time")
        if t.shape[0] > 1 and np.any(np.diff(t) <= 0):
            self.fail("time", "must be strictly increasing")
        return t.shape[0]

    def skeleton(self, T):
        d, fail = self.d, self.fail
        p = d["skeleton_points"]
        if p.ndim != 3 or p.shape[0] != T or p.shape[2] != 3 or p.shape[1] < 2:
            fail("skeleton_points", f"must have shape (T={T}, P>=2, 3), got {p.shape}")
        if d["skeleton_points_unperturbed"].shape != p.shape:
            fail(
                "skeleton_points_unperturbed",
                f"must have the shape of skeleton_points {p.shape}, got {d['skeleton_points_unperturbed'].shape}",
            )
        self.finite("skeleton_points")
        self.finite("skeleton_points_unperturbed")
        e = d["skeleton_edges"]
        if e.ndim != 2 or e.shape[1] != 2 or e.shape[0] < 1 or e.dtype.kind not in "iu":
            fail("skeleton_edges", f"must be an integer array of shape (E>=1, 2), got {e.dtype} {e.shape}")
        if e.min() < 0 or e.max() >= p.shape[1]:
            fail("skeleton_edges", f"indices must lie in [0, {p.shape[1]}), got [{e.min()}, {e.max()}]")
        r = d["skeleton_radii"]
        if r.shape != (e.shape[0],):
            fail("skeleton_radii", f"must have shape (E={e.shape[0]},), got {r.shape}")
        self.finite("skeleton_radii")
        if np.any(r <= 0):
            fail("skeleton_radii", "must be > 0")
        self.vector_series("force_origin", T)

    def vector_series(self, field, T):
        if self.d[field].shape != (T, 3):
            self.fail(field, f"must have shape (T={T}, 3), got {self.d[field].shape}")
        self.finite(field)

    def shapes(self, T):
        d, fail = self.d, self.fail
        v, f = d["shape_vertices"], d["shape_faces"]
        if v.ndim != 2 or v.shape[1] != 3 or v.dtype.kind not in "fi":
            fail("shape_vertices", f"must be a numeric array of shape (V, 3), got {v.dtype} {v.shape}")
        self.finite("shape_vertices")
        if f.ndim != 2 or f.shape[1] != 3 or (f.size and f.dtype.kind not in "iu"):
            fail("shape_faces", f"must be an integer array of shape (F, 3), got {f.dtype} {f.shape}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            fail("shape_faces", f"indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        B = self.poses(T)
        sb = d["shape_body"]
        if sb.shape != (len(v),) or (sb.size and sb.dtype.kind not in "iu"):
            fail("shape_body", f"must be an integer array of shape (V={len(v)},), got {sb.dtype} {sb.shape}")
        if sb.size and (sb.min() < 0 or sb.max() >= B):
            fail("shape_body", f"body indices must lie in [0, {B}), got [{sb.min()}, {sb.max()}]")

    def poses(self, T) -> int:
        pos = self.d["body_pos"]
        if pos.ndim != 3 or pos.shape[0] != T or pos.shape[2] != 3:
            self.fail("body_pos", f"must have shape (T={T}, B, 3), got {pos.shape}")
        B = pos.shape[1]
        for name, shape in (
            ("body_quat", (T, B, 4)),
            ("body_pos_unperturbed", (T, B, 3)),
            ("body_quat_unperturbed", (T, B, 4)),
        ):
            self.shape(name, shape)
        for name in POSE_FIELDS:
            self.finite(name)
        return B

    def optional(self, T):
        d, fail = self.d, self.fail
        if "skeleton_edge_body" in d and "skeleton_edges" in d:
            if d["skeleton_edge_body"].shape != (d["skeleton_edges"].shape[0],):
                fail(
                    "skeleton_edge_body",
                    f"must have shape (E={d['skeleton_edges'].shape[0]},), got {d['skeleton_edge_body'].shape}",
                )
        if "facing" in d:
            if d["facing"].shape != (3,) or not np.all(np.isfinite(d["facing"])):
                fail("facing", f"must be a finite vector of shape (3,), got {d['facing']!r}")
        if "up_axis" in d:
            if d["up_axis"].shape != () or int(d["up_axis"]) not in (0, 1, 2):
                fail("up_axis", f"must be a scalar 0, 1 or 2, got {d['up_axis']!r}")
        if "ball_pos" in d or "ball_radius" in d:
            self.ball(T)
        if "deviation" in d:
            self.shape("deviation", (T,))
            self.finite("deviation")
        if "base_offset" in d:
            self.shape("base_offset", (T, 3))
            self.finite("base_offset")
        if "ground_height" in d:
            self.shape("ground_height", ())
            self.finite("ground_height")
        if "ground_turn" in d or "ground_pivot" in d:
            for name in ("ground_turn", "ground_pivot", "ground_height"):
                if name not in d:
                    fail(name, "is missing: ground_turn, ground_pivot and ground_height come together")
            self.shape("ground_turn", (T, 4))
            self.shape("ground_pivot", (3,))
            self.finite("ground_turn")
            self.finite("ground_pivot")
            norm = np.linalg.norm(np.asarray(d["ground_turn"], float), axis=-1)
            if np.abs(norm - 1.0).max() > 1e-6:
                fail("ground_turn", "must hold unit quaternions")
        if any(f in d for f in RESIDUAL_FIELDS):
            self.residuals(T)
        if "assist_force" in d or "assist_point" in d:
            for name in ("assist_force", "assist_point"):
                if name not in d:
                    fail(name, "is missing (assist_force and assist_point come together)")
                self.vector_series(name, T)
        if "clip_still" in d:
            v = d["clip_still"]
            if v.shape != () or v.dtype.kind not in "fiu" or not (np.isfinite(v) and float(v) >= 0):
                fail("clip_still", f"must be a clip time: a scalar >= 0, got {d['clip_still']!r}")

    def residuals(self, T):
        d, fail = self.d, self.fail
        missing = [f for f in RESIDUAL_FIELDS if f not in d]
        if missing:
            fail(missing[0], "is missing (the residual fields come together)")
        for name in ("residual_force", "residual_moment", "residual_point"):
            self.vector_series(name, T)
        body = d["grf_body"]
        if body.ndim != 1 or (body.size and body.dtype.kind not in "iu"):
            fail("grf_body", f"must be an integer array of shape (K,), got {body.dtype} {body.shape}")
        n_bodies = d["body_names"].shape[0] if "body_names" in d else None
        if body.size and (body.min() < 0 or (n_bodies is not None and body.max() >= n_bodies)):
            fail("grf_body", f"body indices must lie in [0, {n_bodies}), got [{body.min()}, {body.max()}]")
        for name in ("grf_force", "grf_point", "grf_torque"):
            self.shape(name, (T, body.shape[0], 3))
            self.finite(name)
        count = d["contact_points"]
        if count.shape != (T,) or (count.size and (count.dtype.kind not in "iu" or count.min() < 0)):
            fail("contact_points", f"must be non-negative integers of shape (T={T},), got {count.dtype} {count.shape}")
        if json_field(d, "residuals_json") is None:
            fail("residuals_json", "must be a JSON object (a string)")

    def ball(self, T):
        d, fail = self.d, self.fail
        if "ball_pos" not in d or "ball_radius" not in d:
            fail(
                "ball_pos" if "ball_pos" not in d else "ball_radius",
                "is missing (ball_pos and ball_radius come together)",
            )
        if d["ball_pos"].shape != (T, 3):
            fail("ball_pos", f"must have shape (T={T}, 3), got {d['ball_pos'].shape}")
        if d["ball_radius"].size != 1 or not float(d["ball_radius"]) > 0:
            fail("ball_radius", f"must be a positive scalar, got {d['ball_radius']!r}")

    def angles(self, T):
        n = self.d["dof_names"].shape
        if len(n) != 1:
            self.fail("dof_names", f"must have shape (n,), got {n}")
        for f in ("theta", "theta_unperturbed", "theta_desired"):
            if self.d[f].shape != (T, n[0]):
                self.fail(f, f"must have shape (T={T}, n={n[0]}), got {self.d[f].shape}")
            self.finite(f)


def check_run(path, d: Mapping[str, np.ndarray], error: type[ValueError] = RunFileError) -> None:
    """Check the shapes and values of the arrays ``d`` read from ``path``: the drawing fields
    when ``skeleton_points`` is there, the plot fields when ``theta_unperturbed`` is, and every
    optional field present."""
    c = _Checker(path, d, error)
    T = c.time()
    if "skeleton_points" in d:
        c.skeleton(T)
    if "force_vector" in d:
        c.vector_series("force_vector", T)
    if "shape_vertices" in d:
        c.shapes(T)
    c.optional(T)
    if "theta_unperturbed" in d:
        c.angles(T)
