"""Off-screen pictures of a run: a Figure-2 filmstrip, a side-by-side video, and plots.

    render_run("run.npz", "filmstrip.png", frames=6)   # top row original, bottom row perturbed
    render_run("run.npz", "video.mp4")                 # or .gif: both characters side by side
    plot_run("run.npz", "plots.png")                   # deviation and joint angles vs time

Everything reads the RUN.npz contract written by :func:`neuromotor.studies.simulate.run_arrays`
(``skeleton_points``, ``skeleton_points_unperturbed``, ``skeleton_edges``, ``skeleton_radii``,
``force_origin``, ``force_vector``, ``time``, ``up_axis``; ``theta*`` and ``dof_names`` for the
plots; optionally ``ball_pos`` (T,3) and ``ball_radius``, drawn as a sphere; optionally the body
shapes ``shape_vertices`` (V,3, body frame less the body's COM), ``shape_faces`` (F,3),
``shape_body`` (V,) with the poses ``body_pos``/``body_quat`` (w x y z) and their
``_unperturbed`` twins; ``skeleton_edge_body`` (E,) and ``facing`` (3,)).

3-D pictures use pyvista/VTK off screen through EGL and Mesa, so no display and no GPU are needed
(Debian packages ``libegl1 libegl-mesa0 libgl1-mesa-dri``; see ``.ci/install_system_deps.sh``).
This module sets ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` before VTK is imported unless
the variable is already set.

Drawing conventions (also in docs/rendering.md):

* Each body is drawn as the mass model's own convex polyhedron, moved by its pose: a vertex v of
  body b is at ``body_pos[t, b] + R(body_quat[t, b]) @ v``. All bodies of a figure are one mesh
  whose points are recomputed per frame. Bones that carry no body (``skeleton_edge_body`` -1:
  fingers, toes, face) are thin capsules (radius at most ``DETAIL_RADIUS_M``). A run without
  shapes (an older RUN.npz) is drawn as before: capsules of radius ``skeleton_radii`` for every
  bone, joints as spheres slightly wider than the thickest bone meeting there.
* The external force is an arrow whose tip stops 1 cm outside the body surface at the point of
  application and which points along the force; its length is ``|F| / FORCE_SCALE_N_PER_M``
  metres (1 m per 500 N). It is drawn only while ``|F|`` exceeds 1% of its peak.
* The camera looks at the character's front: its horizontal direction is the facing direction
  (``facing``, else :func:`facing_from_skeleton`) turned by ``CAMERA_AZIMUTH_DEG`` (40 degrees)
  about the up axis, to the side that sees the hit most side-on (on a tie, the side the hit comes
  from), and it is raised by ``CAMERA_ELEVATION_DEG`` (12 degrees); see :func:`camera_view`. The
  picture is therefore the same whatever the up axis and heading. Parallel projection keeps the
  scale identical in every panel.

Outputs are written to a temporary file beside the target and renamed, so a failed render never
leaves a partial file. Bad input raises :class:`RenderError` (a ``ValueError``) naming the file
and the field.
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np

from neuromotor.io.atomic import atomic_path
FORCE_SCALE_N_PER_M = 500.0   # arrow length: 1 m per 500 N
FORCE_VISIBLE_FRACTION = 0.01  # draw the arrow while |F| > 1% of its peak
CAMERA_ELEVATION_DEG = 12.0  # camera raised above the horizontal
CAMERA_AZIMUTH_DEG = 40.0    # camera turned this far from the character's facing direction
DETAIL_RADIUS_M = 0.015      # thickest capsule drawn for a bone that carries no body
VIDEO_SIZE = (640, 360)        # pixels per video frame (width, height)
PANEL_SIZE = (300, 420)        # pixels per filmstrip panel (width, height)
VIDEO_FPS = {".mp4": 30.0, ".gif": 25.0}  # GIF delays are whole centiseconds: 40 ms is exact

IMAGE_EXTENSIONS = (".png",)
VIDEO_EXTENSIONS = (".mp4", ".gif")

COLOR_ORIGINAL = (0.52, 0.64, 0.84)       # blue-grey
COLOR_ORIGINAL_JOINT = (0.36, 0.47, 0.68)
COLOR_ORIGINAL_VIDEO = (0.66, 0.76, 0.92)  # lighter, for the original beside the perturbed one
COLOR_GHOST = (0.80, 0.84, 0.90)          # the original, drawn behind the perturbed one
COLOR_GHOST_JOINT = (0.72, 0.77, 0.85)
COLOR_PERTURBED = (0.90, 0.45, 0.20)      # orange
COLOR_PERTURBED_JOINT = (0.62, 0.26, 0.10)
COLOR_FORCE = (0.85, 0.05, 0.05)
COLOR_BALL = (0.95, 0.85, 0.15)
GROUND_COLORS = ((0.93, 0.93, 0.91), (0.84, 0.84, 0.82))
GROUND_TILE_M = 0.5


class RenderError(ValueError):
    """Bad input or output for rendering; the message names the file and the field."""


# ----------------------------------------------------------------------------------------------
# Input
# ----------------------------------------------------------------------------------------------

_SKELETON_FIELDS = ("time", "skeleton_points", "skeleton_points_unperturbed", "skeleton_edges",
                    "skeleton_radii", "force_origin", "force_vector")
_PLOT_FIELDS = ("time", "dof_names", "theta", "theta_unperturbed", "theta_desired", "force_vector")


_OPTIONAL_FIELDS = ("up_axis", "ball_pos", "ball_radius", "metrics_json", "facing", "skeleton_edge_body",
                    "contact_force", "provenance_json")
# Body shapes: all of them, or (an older RUN.npz) none and capsules are drawn instead.
_SHAPE_FIELDS = ("shape_vertices", "shape_faces", "shape_body", "body_pos", "body_quat",
                 "body_pos_unperturbed", "body_quat_unperturbed")


def load_run(run_path, fields=_SKELETON_FIELDS) -> dict[str, np.ndarray]:
    """Read and check the arrays of a RUN.npz needed for drawing (``fields``) plus the optional
    ``up_axis``, ``ball_pos``, ``ball_radius``, ``metrics_json``, ``facing``,
    ``skeleton_edge_body`` and (when drawing, all or none) the body shapes and poses
    ``shape_vertices``, ``shape_faces``, ``shape_body``, ``body_pos``, ``body_quat`` and their
    ``_unperturbed`` twins."""
    path = pathlib.Path(run_path)
    if not path.is_file():
        raise RenderError(f"{path}: no such run file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            names = set(npz.files)
            missing = [f for f in fields if f not in names]
            if missing:
                raise RenderError(f"{path}: missing array(s) {', '.join(missing)} "
                                  f"(not a RUN.npz from `neuromotor simulate`?)")
            wanted = set(fields) | (set(_OPTIONAL_FIELDS) & names)
            if "skeleton_points" in fields and "shape_vertices" in names:
                missing = [f for f in _SHAPE_FIELDS if f not in names]
                if missing:
                    raise RenderError(f"{path}: has shape_vertices but lacks array(s) "
                                      f"{', '.join(missing)} needed to draw the body shapes")
                wanted |= set(_SHAPE_FIELDS)
            data = {k: np.asarray(npz[k]) for k in wanted}
    except RenderError:
        raise
    except Exception as e:  # zipfile.BadZipFile, ValueError (pickled object arrays), OSError
        raise RenderError(f"{path}: cannot read as .npz: {e}") from None
    _check(path, data)
    return data


def _check(path, d):
    def fail(field, msg):
        raise RenderError(f"{path}: field '{field}' {msg}")

    def finite(field):
        if not np.all(np.isfinite(d[field])):
            fail(field, "contains non-finite values (did the simulation diverge?)")

    t = d["time"]
    if t.ndim != 1 or t.shape[0] < 1:
        fail("time", f"must have shape (T,), got {t.shape}")
    if t.dtype.kind not in "fi":
        fail("time", f"must be numeric, got dtype {t.dtype}")
    finite("time")
    if t.shape[0] > 1 and np.any(np.diff(t) <= 0):
        fail("time", "must be strictly increasing")
    T = t.shape[0]
    if "skeleton_points" in d:
        p = d["skeleton_points"]
        if p.ndim != 3 or p.shape[0] != T or p.shape[2] != 3 or p.shape[1] < 2:
            fail("skeleton_points", f"must have shape (T={T}, P>=2, 3), got {p.shape}")
        if d["skeleton_points_unperturbed"].shape != p.shape:
            fail("skeleton_points_unperturbed",
                 f"must have the shape of skeleton_points {p.shape}, got "
                 f"{d['skeleton_points_unperturbed'].shape}")
        finite("skeleton_points")
        finite("skeleton_points_unperturbed")
        e = d["skeleton_edges"]
        if e.ndim != 2 or e.shape[1] != 2 or e.shape[0] < 1 or e.dtype.kind not in "iu":
            fail("skeleton_edges", f"must be an integer array of shape (E>=1, 2), got {e.dtype} {e.shape}")
        if e.min() < 0 or e.max() >= p.shape[1]:
            fail("skeleton_edges", f"indices must lie in [0, {p.shape[1]}), got [{e.min()}, {e.max()}]")
        r = d["skeleton_radii"]
        if r.shape != (e.shape[0],):
            fail("skeleton_radii", f"must have shape (E={e.shape[0]},), got {r.shape}")
        finite("skeleton_radii")
        if np.any(r <= 0):
            fail("skeleton_radii", "must be > 0")
        for f in ("force_origin",):
            if d[f].shape != (T, 3):
                fail(f, f"must have shape (T={T}, 3), got {d[f].shape}")
            finite(f)
    if d["force_vector"].shape != (T, 3):
        fail("force_vector", f"must have shape (T={T}, 3), got {d['force_vector'].shape}")
    finite("force_vector")
    if "shape_vertices" in d:
        v, f, sb = d["shape_vertices"], d["shape_faces"], d["shape_body"]
        if v.ndim != 2 or v.shape[1] != 3 or v.dtype.kind not in "fi":
            fail("shape_vertices", f"must be a numeric array of shape (V, 3), got {v.dtype} {v.shape}")
        finite("shape_vertices")
        if f.ndim != 2 or f.shape[1] != 3 or (f.size and f.dtype.kind not in "iu"):
            fail("shape_faces", f"must be an integer array of shape (F, 3), got {f.dtype} {f.shape}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            fail("shape_faces", f"indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        pos = d["body_pos"]
        if pos.ndim != 3 or pos.shape[0] != T or pos.shape[2] != 3:
            fail("body_pos", f"must have shape (T={T}, B, 3), got {pos.shape}")
        B = pos.shape[1]
        for name, shape in (("body_quat", (T, B, 4)), ("body_pos_unperturbed", (T, B, 3)),
                            ("body_quat_unperturbed", (T, B, 4))):
            if d[name].shape != shape:
                fail(name, f"must have shape {shape}, got {d[name].shape}")
        for name in ("body_pos", "body_quat", "body_pos_unperturbed", "body_quat_unperturbed"):
            finite(name)
        if sb.shape != (len(v),) or (sb.size and sb.dtype.kind not in "iu"):
            fail("shape_body", f"must be an integer array of shape (V={len(v)},), got {sb.dtype} {sb.shape}")
        if sb.size and (sb.min() < 0 or sb.max() >= B):
            fail("shape_body", f"body indices must lie in [0, {B}), got [{sb.min()}, {sb.max()}]")
    if "skeleton_edge_body" in d and "skeleton_edges" in d:
        if d["skeleton_edge_body"].shape != (d["skeleton_edges"].shape[0],):
            fail("skeleton_edge_body", f"must have shape (E={d['skeleton_edges'].shape[0]},), "
                                       f"got {d['skeleton_edge_body'].shape}")
    if "facing" in d:
        if d["facing"].shape != (3,) or not np.all(np.isfinite(d["facing"])):
            fail("facing", f"must be a finite vector of shape (3,), got {d['facing']!r}")
    if "up_axis" in d:
        if d["up_axis"].shape != () or int(d["up_axis"]) not in (0, 1, 2):
            fail("up_axis", f"must be a scalar 0, 1 or 2, got {d['up_axis']!r}")
    if "ball_pos" in d or "ball_radius" in d:
        if "ball_pos" not in d or "ball_radius" not in d:
            fail("ball_pos" if "ball_pos" not in d else "ball_radius",
                 "is missing (ball_pos and ball_radius come together)")
        if d["ball_pos"].shape != (T, 3):
            fail("ball_pos", f"must have shape (T={T}, 3), got {d['ball_pos'].shape}")
        if d["ball_radius"].size != 1 or not float(d["ball_radius"]) > 0:
            fail("ball_radius", f"must be a positive scalar, got {d['ball_radius']!r}")
    if "theta" in d:
        n = d["dof_names"].shape
        if len(n) != 1:
            fail("dof_names", f"must have shape (n,), got {n}")
        for f in ("theta", "theta_unperturbed", "theta_desired"):
            if d[f].shape != (T, n[0]):
                fail(f, f"must have shape (T={T}, n={n[0]}), got {d[f].shape}")
            finite(f)


# ----------------------------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------------------------

def _write_png(path, img):
    import imageio.v3 as iio

    iio.imwrite(path, np.ascontiguousarray(img), extension=".png")


# ----------------------------------------------------------------------------------------------
# Geometry: fixed-topology meshes whose points are recomputed per frame
# ----------------------------------------------------------------------------------------------

def _unit(v, fallback):
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else np.asarray(fallback, float)


def _poly(points, faces, nverts):
    import pyvista as pv

    faces = np.asarray(faces).reshape(-1, nverts)
    return pv.PolyData(points, np.hstack([np.full((len(faces), 1), nverts), faces]).ravel())


class _SkeletonGeometry:
    """Capsule bones and joint spheres for one skeleton, as two meshes of fixed topology whose
    points are recomputed by :meth:`update` (no actors are rebuilt per frame).

    Bone e is a cylinder of radius ``radii[e]`` closed by spheres of the same radius at both ends
    (a capsule). A point shared by two or more bones gets a joint sphere of 1.3 times its
    thinnest bone's radius, capped at its thickest bone's radius + 1 cm so that joints of thin
    limbs show while joints inside the thick trunk do not bulge.
    """

    def __init__(self, edges, radii, n_points, sides=16, lat=10, lon=16):
        import pyvista as pv

        self.edges = np.asarray(edges, int)
        self.radii = np.asarray(radii, float)
        E, S = len(self.edges), sides
        deg = np.bincount(self.edges.ravel(), minlength=n_points)
        rmin, rmax = np.full(n_points, np.inf), np.zeros(n_points)
        for (a, b), r in zip(self.edges, self.radii):
            for i in (a, b):
                rmin[i], rmax[i] = min(rmin[i], r), max(rmax[i], r)
        self.joint_idx = np.flatnonzero(deg >= 2)
        self.joint_radii = np.minimum(1.3 * rmin, rmax + 0.01)[self.joint_idx]
        # Cylinder template: two rings per bone.
        ang = np.linspace(0.0, 2 * np.pi, S, endpoint=False)
        self.cos, self.sin = np.cos(ang), np.sin(ang)
        j = np.arange(S)
        quads = np.stack([j, (j + 1) % S, S + (j + 1) % S, S + j], axis=1)
        cyl_faces = ((np.arange(E) * 2 * S)[:, None, None] + quads[None]).reshape(-1, 4)
        # Sphere template, as triangles (caps appended after the cylinders).
        sph = pv.Sphere(radius=1.0, theta_resolution=lon, phi_resolution=lat).triangulate()
        self.sph_dirs = np.asarray(sph.points, float)
        nv = len(self.sph_dirs)
        tri = sph.faces.reshape(-1, 4)[:, 1:]
        cap_base = E * 2 * S

        def spheres(count, base):
            return (base + (np.arange(count) * nv)[:, None, None] + tri[None]).reshape(-1, 3)

        # Quads and triangles in one PolyData: split the cylinder quads into triangles.
        cyl_tris = np.concatenate([cyl_faces[:, [0, 1, 2]], cyl_faces[:, [0, 2, 3]]])
        self.bones = _poly(np.zeros((cap_base + 2 * E * nv, 3)),
                           np.concatenate([cyl_tris, spheres(2 * E, cap_base)]), 3)
        self.cap_normals = np.tile(self.sph_dirs, (2 * E, 1))
        J = len(self.joint_idx)
        self.joints = _poly(np.zeros((max(J, 1) * nv, 3)), spheres(max(J, 1), 0), 3)
        self.joints.point_data["Normals"] = np.tile(self.sph_dirs, (max(J, 1), 1))
        self.joints.point_data.active_normals_name = "Normals"
        self.update(np.arange(n_points)[:, None] * np.array([1e-3, 2e-3, 3e-3]))

    def update(self, points):
        points = np.asarray(points, float)
        a, b = points[self.edges[:, 0]], points[self.edges[:, 1]]
        axis = b - a
        length = np.linalg.norm(axis, axis=1, keepdims=True)
        ok = length > 1e-9
        axis = np.where(ok, axis / np.where(ok, length, 1.0), [0.0, 0.0, 1.0])
        helper = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(axis, e1)
        normal = self.cos[None, :, None] * e1[:, None, :] + self.sin[None, :, None] * e2[:, None, :]
        ring = self.radii[:, None, None] * normal                                  # (E, S, 3)
        cyl = np.concatenate([a[:, None] + ring, b[:, None] + ring], axis=1)      # (E, 2S, 3)
        ends = np.concatenate([a, b])                                             # (2E, 3)
        rr = np.concatenate([self.radii, self.radii])
        caps = ends[:, None] + rr[:, None, None] * self.sph_dirs[None]
        self.bones.points = np.concatenate([cyl.reshape(-1, 3), caps.reshape(-1, 3)])
        self.bones.point_data["Normals"] = np.concatenate(
            [np.concatenate([normal, normal], axis=1).reshape(-1, 3), self.cap_normals])
        self.bones.point_data.active_normals_name = "Normals"
        if len(self.joint_idx):
            c = points[self.joint_idx]
            self.joints.points = (c[:, None] + self.joint_radii[:, None, None] * self.sph_dirs[None]).reshape(-1, 3)
        else:  # a single chain of two points: hide the placeholder joint inside the first point
            self.joints.points = np.repeat(points[:1], len(self.sph_dirs), axis=0)


class _ArrowGeometry:
    """An arrow of fixed topology (shaft + cone) with absolute shaft and head sizes in metres."""

    def __init__(self, shaft_radius=0.022, head_radius=0.055, head_length=0.14, sides=16):
        import pyvista as pv

        self.rs, self.rh, self.lh = shaft_radius, head_radius, head_length
        ang = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
        self.cs, self.sn = np.cos(ang), np.sin(ang)
        S = sides
        j = np.arange(S)
        jn = (j + 1) % S
        # Rings: 0 shaft tail, 1 shaft top, 2 head base (wide); then tip and tail-centre points.
        quads = [np.stack([j, jn, S + jn, S + j], 1),            # shaft side
                 np.stack([S + j, S + jn, 2 * S + jn, 2 * S + j], 1)]  # head base annulus
        tris = [np.stack([2 * S + j, 2 * S + jn, np.full(S, 3 * S)], 1),   # cone
                np.stack([jn, j, np.full(S, 3 * S + 1)], 1)]               # tail cap
        cells = [np.hstack([np.full((S, 1), 4), q]) for q in quads]
        cells += [np.hstack([np.full((S, 1), 3), t]) for t in tris]
        self.mesh = pv.PolyData(np.zeros((3 * S + 2, 3)), np.concatenate([c.ravel() for c in cells]))
        self.update(np.zeros(3), np.array([1.0, 0.0, 0.0]))

    def update(self, tail, tip):
        tail, tip = np.asarray(tail, float), np.asarray(tip, float)
        d = tip - tail
        L = max(np.linalg.norm(d), 1e-6)
        u = _unit(d, [1.0, 0.0, 0.0])
        helper = [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]
        e1 = _unit(np.cross(u, helper), [0.0, 1.0, 0.0])
        e2 = np.cross(u, e1)
        lh = min(self.lh, 0.5 * L)
        ring = self.cs[:, None] * e1 + self.sn[:, None] * e2
        head_base = tip - lh * u
        pts = np.concatenate([tail + self.rs * ring, head_base + self.rs * ring,
                              head_base + self.rh * ring, tip[None], tail[None]])
        self.mesh.points = pts


def quat_matrices(q):
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in w x y z order (normalised)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


class _BodyGeometry:
    """Every body's polyhedron of one figure as a single mesh of fixed topology, moved rigidly by
    :meth:`update` (body poses) without rebuilding any actor.

    ``vertices`` are in the body frames relative to the COM, so a vertex of body b lands at
    ``pos[b] + rot[b] @ v``. Vertex normals are computed once, in the body frames, with vertices
    split along edges sharper than ``feature_angle`` degrees (round limbs shade smoothly, the
    edges of flat hands and feet stay crisp), and are rotated with their bodies.
    """

    def __init__(self, vertices, faces, owner, feature_angle=50.0):
        import pyvista as pv

        vertices = np.asarray(vertices, float)
        base = _poly(vertices, np.asarray(faces, int), 3)
        split = base.compute_normals(cell_normals=False, split_vertices=True, consistent_normals=False,
                                     auto_orient_normals=False, feature_angle=feature_angle)
        ids = np.asarray(split.point_data["pyvistaOriginalPointIds"], int)
        self.local = vertices[ids]
        self.local_normals = np.asarray(split.point_data["Normals"], float)
        self.owner = np.asarray(owner, int)[ids]
        self.mesh = pv.PolyData(self.local.copy(), np.asarray(split.faces))
        self.n_faces = len(faces)

    def update(self, pos, rot):
        R = np.asarray(rot, float)[self.owner]
        self.mesh.points = np.asarray(pos, float)[self.owner] + np.einsum("vij,vj->vi", R, self.local)
        self.mesh.point_data["Normals"] = np.einsum("vij,vj->vi", R, self.local_normals)
        self.mesh.point_data.active_normals_name = "Normals"


class _FigureGeometry:
    """One figure as drawn: the bodies' polyhedra (when the run has them) plus thin capsules for
    the bones that carry no body (fingers, toes, face), or, for a run without shapes, capsules
    for every bone."""

    def __init__(self, scene):
        self.scene = scene
        self.bodies = None
        if scene.has_shapes:
            d = scene.d
            self.bodies = _BodyGeometry(d["shape_vertices"], d["shape_faces"], d["shape_body"])
        self.capsules = None
        if len(scene.capsule_edges):
            self.capsules = _SkeletonGeometry(scene.capsule_edges, scene.capsule_radii, scene.P.shape[1])

    def update(self, k, which, offset=np.zeros(3)):
        s = self.scene
        if self.bodies is not None:
            pos, rot = s.body_pose(k, which)
            self.bodies.update(pos + offset, rot)
        if self.capsules is not None:
            self.capsules.update(s.points(which)[k] + offset)
        return self

    def meshes(self):
        out = [self.bodies.mesh] if self.bodies is not None else []
        if self.capsules is not None:
            out += [self.capsules.bones, self.capsules.joints]
        return out

    def add(self, pl, color, joint_color, specular=0.25):
        if self.bodies is not None:
            actor = pl.add_mesh(self.bodies.mesh, color=color, smooth_shading=False, specular=specular,
                                specular_power=20)
            actor.prop.interpolation = "phong"
        if self.capsules is not None:
            # Detail bones beside bodies are drawn in the darker joint colour.
            _add_skeleton(pl, self.capsules, joint_color if self.bodies is not None else color,
                          joint_color, specular=specular)


def _horizontal(v, up):
    v = np.asarray(v, float)
    return v - (v @ up)[..., None] * up


def _turn(v, up, angle):
    """Rotate the horizontal vector ``v`` about ``up`` by ``angle`` radians (right-handed)."""
    return np.cos(angle) * v + np.sin(angle) * np.cross(up, v)


def facing_from_skeleton(points, edges, up_axis: int = 1) -> np.ndarray:
    """The character's horizontal facing direction (a world unit vector perpendicular to the up
    axis), estimated from skeleton points alone, for runs that do not store ``facing``.

    ``points`` (T,P,3) or (P,3), ``edges`` (E,2) parent -> child pairs. The feet are the two
    lowest leaves of the tree (on average over time); the legs are their chains up to the joint
    they share (the pelvis). The left-right axis runs between the two legs' top points (between
    the legs' mean points if the tops coincide), and the facing is horizontal and perpendicular
    to it, on the side the feet point to (leaf minus its parent point: toes, or the foot bone),
    or, when the feet do not tell, the side the root travels to. Averaged over all samples, so a
    walking gait's scissoring cancels. Without two feet it falls back to the travel direction.
    """
    P = np.asarray(points, float)
    if P.ndim == 2:
        P = P[None]
    up = np.eye(3)[int(up_axis)]
    other = np.eye(3)[(int(up_axis) + 2) % 3]
    edges = np.asarray(edges, int).reshape(-1, 2)
    n = P.shape[1]
    parent = np.full(n, -1)
    parent[edges[:, 1]] = edges[:, 0]
    degree = np.bincount(edges.ravel(), minlength=n)
    root = int(np.flatnonzero(parent < 0)[0]) if np.any(parent < 0) else 0
    travel = _horizontal(P[-1, root] - P[0, root], up)
    leaves = [i for i in range(n) if degree[i] == 1 and parent[i] >= 0]
    if len(leaves) < 2:
        return _unit(travel, other) if np.linalg.norm(travel) > 0.05 else other

    def chain(i):
        out = []
        while i >= 0:
            out.append(i)
            i = parent[i]
        return out[::-1]   # root first

    height = (P @ up).mean(axis=0)
    feet = sorted(leaves, key=lambda i: height[i])[:2]
    a, b = chain(feet[0]), chain(feet[1])
    shared = 0
    while shared < min(len(a), len(b)) and a[shared] == b[shared]:
        shared += 1
    la, lb = a[shared:], b[shared:]
    lateral = _horizontal(P[:, la[0]] - P[:, lb[0]], up).mean(axis=0)
    if np.linalg.norm(lateral) < 0.05:
        lateral = _horizontal(P[:, la].mean(axis=1) - P[:, lb].mean(axis=1), up).mean(axis=0)
    if np.linalg.norm(lateral) < 1e-6:
        return _unit(travel, other) if np.linalg.norm(travel) > 0.05 else other
    forward = _unit(np.cross(lateral, up), other)
    toes = sum(_horizontal(P[:, f] - P[:, parent[f]], up).mean(axis=0) for f in feet)
    if abs(toes @ forward) > 0.2 * max(np.linalg.norm(toes), 1e-9) and np.linalg.norm(toes) > 0.02:
        return forward if toes @ forward > 0 else -forward
    if abs(travel @ forward) > 0.05:
        return forward if travel @ forward > 0 else -forward
    return forward


def facing_direction(points, edges, up_axis: int = 1, forward=None) -> np.ndarray:
    """``forward`` (a world direction, e.g. from the character's anatomy) made horizontal and
    unit, or :func:`facing_from_skeleton` when it is missing or (nearly) vertical."""
    up = np.eye(3)[int(up_axis)]
    if forward is not None:
        f = _horizontal(np.asarray(forward, float).reshape(3), up)
        if np.all(np.isfinite(f)) and np.linalg.norm(f) > 1e-3:
            return f / np.linalg.norm(f)
    return facing_from_skeleton(points, edges, up_axis)


def camera_view(facing, up, hit=None, azimuth_deg=CAMERA_AZIMUTH_DEG, elevation_deg=CAMERA_ELEVATION_DEG):
    """Unit vector from the scene towards the camera: the horizontal ``facing`` turned by
    ``azimuth_deg`` about ``up`` (a three-quarter front view), then raised by ``elevation_deg``.

    Of the two turns (counter-clockwise or clockwise about ``up``) it takes the one that sees
    the horizontal ``hit`` direction most side-on, so that the force arrow is long on screen. On
    a tie in that (a push from the side) it takes the one where the force points away from the
    camera, so the arrow starts on the camera's side of the body; on a push from straight in
    front or behind, or without a hit, the counter-clockwise turn.
    """
    up = np.asarray(up, float)
    f = _unit(_horizontal(facing, up), np.roll(up, 1))
    az = np.radians(azimuth_deg)
    candidates = [_turn(f, up, az), _turn(f, up, -az)]
    best = candidates[0]
    if hit is not None and np.linalg.norm(_horizontal(hit, up)) > 1e-9:
        h = _unit(_horizontal(hit, up), f)
        score = [abs(h @ c) + 0.25 * (h @ c) for c in candidates]
        if score[1] < score[0] - 1e-9:
            best = candidates[1]
    el = np.radians(elevation_deg)
    return np.cos(el) * best + np.sin(el) * up


# ----------------------------------------------------------------------------------------------
# Scene analysis: hit window, camera directions, ground
# ----------------------------------------------------------------------------------------------

class _Scene:
    def __init__(self, d):
        self.d = d
        self.time = d["time"].astype(float)
        self.P = d["skeleton_points"].astype(float)
        self.U = d["skeleton_points_unperturbed"].astype(float)
        self.up_axis = int(d.get("up_axis", 1))
        self.up = np.eye(3)[self.up_axis]
        self.F = d["force_vector"].astype(float)
        self.Fo = d["force_origin"].astype(float)
        fmag = np.linalg.norm(self.F, axis=1)
        self.fmag = fmag
        self.force_on = fmag > FORCE_VISIBLE_FRACTION * fmag.max() if fmag.max() > 0 else np.zeros(len(fmag), bool)
        edges, radii = d["skeleton_edges"].astype(int), d["skeleton_radii"].astype(float)
        # Body shapes (world = body_pos + R(body_quat) @ v), or none: capsules for every bone.
        self.has_shapes = "shape_vertices" in d and len(d["shape_vertices"]) > 0 and len(d["shape_faces"]) > 0
        if self.has_shapes:
            self.shape_v = d["shape_vertices"].astype(float)
            self.shape_b = d["shape_body"].astype(int)
            self.body_pos = {"perturbed": d["body_pos"].astype(float),
                             "original": d["body_pos_unperturbed"].astype(float)}
            self.body_rot = {"perturbed": quat_matrices(d["body_quat"]),
                             "original": quat_matrices(d["body_quat_unperturbed"])}
            # Face planes per vertex-owner for the convex-body queries (arrow tip, detail bones).
            f = d["shape_faces"].astype(int)
            self.face_body = self.shape_b[f[:, 0]]
            self.faces = f
            if "skeleton_edge_body" in d:
                detail = d["skeleton_edge_body"].astype(int) < 0
            else:  # an edge is detail if its midpoint lies in no body (at the first sample)
                mid = 0.5 * (self.U[0][edges[:, 0]] + self.U[0][edges[:, 1]])
                detail = np.array([self._inside_bodies(0, "original", m).size == 0 for m in mid], bool)
            self.capsule_edges = edges[detail]
            self.capsule_radii = np.minimum(radii[detail], DETAIL_RADIUS_M)
        else:
            self.capsule_edges, self.capsule_radii = edges, radii
        self.pad = 1.25 * float(self.capsule_radii.max()) if len(self.capsule_radii) else 0.0
        # Horizontal direction of the hit (at its peak), if any.
        self.hit_dir = _horizontal(self.F[int(np.argmax(fmag))], self.up) if fmag.max() > 0 else None
        # The character's facing direction, and the camera: a three-quarter front view.
        self.facing = facing_direction(self.U, edges, self.up_axis, d.get("facing"))
        self.view = camera_view(self.facing, self.up, self.hit_dir)   # from the scene to the camera
        self.right = _unit(np.cross(self.up, self.view), np.roll(self.up, 2))
        self.screen_up = np.cross(self.view, self.right)
        self.screen_up /= np.linalg.norm(self.screen_up)
        # Ground: touching the lowest surface of either figure over the whole run.
        low = np.inf
        for which in ("perturbed", "original"):
            if self.has_shapes:
                pos, rot = self.body_pos[which], self.body_rot[which]
                h = (pos[:, self.shape_b] @ self.up
                     + np.einsum("tvj,vj->tv", rot[:, self.shape_b, self.up_axis, :], self.shape_v))
                low = min(low, float(h.min()))
            if len(self.capsule_edges):
                e, r = self.capsule_edges, self.capsule_radii
                h = self.points(which) @ self.up                           # (T, P)
                low = min(low, float((np.minimum(h[:, e[:, 0]], h[:, e[:, 1]]) - r).min()))
        self.ground = low
        if "ball_pos" in d:
            hb = d["ball_pos"] @ self.up - float(d["ball_radius"])
            self.ground = min(self.ground, float(hb.min()))
        self.has_ball = "ball_pos" in d
        # What hits the character over time (N): the applied force, or the ball's contact force.
        hit = fmag.copy()
        if "contact_force" in d and np.ndim(d["contact_force"]) == 3 and len(d["contact_force"]) == len(fmag):
            hit = np.maximum(hit, np.linalg.norm(np.asarray(d["contact_force"], float).sum(axis=1), axis=1))
        self.hit_mag = hit
        self.hit_on = hit > FORCE_VISIBLE_FRACTION * hit.max() if hit.max() > 0 else np.zeros(len(hit), bool)
        self.metrics = _json_field(d, "metrics_json")
        self.provenance = _json_field(d, "provenance_json")

    def force_label(self, k):
        """Label of the force drawn at sample k: the configured peak magnitude of the pulse acting
        then (from the run's provenance), else the largest sampled |F| of the hit, not the
        sampled value at k (a half-sine's samples are below its peak)."""
        t = float(self.time[k])
        for p in (self.provenance or {}).get("perturbations", []):
            try:
                start, dur, mag = float(p["start"]), float(p["duration"]), float(p["magnitude"])
            except (KeyError, TypeError, ValueError):
                continue
            if start - 1e-9 <= t <= start + max(dur, float(self.time[1] - self.time[0]) if len(self.time) > 1 else dur):
                unit = "N s" if p.get("kind") == "impulse" else "N"
                return f"{mag:.0f} {unit}"
        on = np.flatnonzero(self.force_on)
        peak = float(self.fmag[on].max()) if len(on) else float(self.fmag[k])
        return f"{peak:.0f} N"

    def points(self, which):
        return self.P if which == "perturbed" else self.U

    def body_pose(self, k, which):
        """(B,3) COM positions and (B,3,3) rotations of the bodies at sample k."""
        return self.body_pos[which][k], self.body_rot[which][k]

    def shape_points(self, k, which):
        """(V,3) world positions of all body-shape vertices at sample k."""
        pos, rot = self.body_pose(k, which)
        return pos[self.shape_b] + np.einsum("vij,vj->vi", rot[self.shape_b], self.shape_v)

    def _planes(self, k, which):
        """Outward unit normals and offsets (n . x = c) of every shape face at sample k."""
        w = self.shape_points(k, which)
        a, b, c = w[self.faces[:, 0]], w[self.faces[:, 1]], w[self.faces[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-14
        n = n[ok] / norm[ok, None]
        return n, np.einsum("ij,ij->i", n, a[ok]), self.face_body[ok]

    def _inside_bodies(self, k, which, x, tol=1e-9):
        """Bodies whose (convex) shape contains the point x at sample k."""
        n, c, owner = self._planes(k, which)
        outside = (n @ x - c) > tol
        bodies = np.unique(owner)
        return np.array([b for b in bodies if not outside[owner == b].any()], int)

    def arrow(self, k):
        """(tail, tip) of the force arrow at sample k. It points along the force, is
        ``|F| / FORCE_SCALE_N_PER_M`` long, and its tip stops at the surface of the body at the
        point of application (which usually lies inside the body)."""
        o, f = self.Fo[k], self.F[k]
        u = _unit(f, [1.0, 0.0, 0.0])
        tip = o - u * self.surface_depth(k)
        return tip - f / FORCE_SCALE_N_PER_M, tip

    def surface_depth(self, k):
        """How far back from the application point along the force the body's surface lies, plus
        1 cm: where the ray backwards leaves the (convex) body shapes containing the point, or,
        without shapes, the nearest capsule's radius less the point's distance from its axis."""
        o = self.Fo[k]
        u = _unit(self.F[k], [1.0, 0.0, 0.0])
        if self.has_shapes:
            n, c, owner = self._planes(k, "perturbed")
            depth = 0.0
            for b in self._inside_bodies(k, "perturbed", o):
                nb, cb = n[owner == b], c[owner == b]
                leaving = nb @ -u > 1e-12
                if leaving.any():
                    depth = max(depth, float(np.min((cb[leaving] - nb[leaving] @ o) / (nb[leaving] @ -u))))
            return depth + 0.01
        edges, radii = self.d["skeleton_edges"], self.d["skeleton_radii"]
        a, b = self.P[k][edges[:, 0]], self.P[k][edges[:, 1]]
        ab = b - a
        s = np.clip(np.einsum("ij,ij->i", o - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
        dist = np.linalg.norm(a + s[:, None] * ab - o, axis=1)
        inside = radii - dist
        return float(max(inside.max(), 0.0)) + 0.01

    def hit_window(self):
        """(first, last) index of samples where the character is hit (an applied force, or a
        ball's contact force), or None."""
        on = np.flatnonzero(self.hit_on)
        return (int(on[0]), int(on[-1])) if len(on) else None

    def filmstrip_key_times(self):
        """(t_hit, t_peak, t_end) of the strip: the instant of the largest hit force, the peak
        deviation (the later of the skeleton's point-wise peak and the metrics' joint-angle
        peak), and the recovery (metrics' recovery time, else the point-wise deviation decayed
        to 25% of its peak), at least 0.4 s after the hit ends and 0.25 s after the peak, capped
        by the run's end. None without a hit."""
        t = self.time
        win = self.hit_window()
        if win is None:
            return None
        t_on, t_off = t[win[0]], t[win[1]]
        t_hit = float(t[win[0] + int(np.argmax(self.hit_mag[win[0]:win[1] + 1]))])
        dev = np.linalg.norm(self.P - self.U, axis=2).max(axis=1)
        after = np.flatnonzero(t >= t_on)
        kpk = after[int(np.argmax(dev[after]))]
        t_pk = float(t[kpk])
        m = self.metrics or {}
        tp = m.get("time_of_peak_s")
        if isinstance(tp, (int, float)) and np.isfinite(tp) and t_on <= tp <= t[-1]:
            t_pk = max(t_pk, float(tp))
        later = np.flatnonzero((t > t_pk) & (dev < 0.25 * dev[kpk]))
        t_end = float(t[later[0]]) if len(later) else float(t[-1])
        rec = m.get("recovery_time_s")
        if isinstance(rec, (int, float)) and np.isfinite(rec):
            t_end = max(t_end, t_on + float(rec))
        t_end = float(min(t[-1], max(t_end, t_off + 0.4, t_pk + 0.25)))
        return t_hit, min(t_pk, t_end), t_end

    def filmstrip_times(self, n):
        """Instants of an n-panel strip: evenly spaced from one step before the hit to the
        recovery, with the panels nearest the hit and the peak moved onto them (n = 1: the hit;
        2: hit and peak; 3: hit, peak, recovery)."""
        t = self.time
        keys = self.filmstrip_key_times()
        if keys is None:
            return np.linspace(t[0], t[-1], n)
        t_hit, t_pk, t_end = keys
        if n <= 3:
            return np.asarray([t_hit, t_pk, t_end][:n], float)
        t_on = t[self.hit_window()[0]]
        span = max(t_end - t_on, 1e-9)
        t_start = max(t[0], t_on - span / (n - 1))   # one panel before the hit
        times = np.linspace(t_start, t_end, n)
        free = list(range(1, n - 1))  # the first (before) and last (recovery) panels stay
        for key in (t_hit, t_pk):
            if any(abs(times[i] - key) < 1e-12 for i in range(n)):
                continue
            j = min(free, key=lambda i: abs(times[i] - key))
            times[j] = key
            free.remove(j)
        return np.sort(times)

    def index_at(self, times):
        """Nearest sample of each time."""
        t = self.time
        times = np.asarray(times, float)
        hi = np.clip(np.searchsorted(t, times), 1, len(t) - 1) if len(t) > 1 else np.zeros(len(times), int)
        if len(t) == 1:
            return hi
        lo = hi - 1
        return np.where(np.abs(t[lo] - times) <= np.abs(t[hi] - times), lo, hi)

    def extent_points(self, k, which, offset=np.zeros(3)):
        """Points whose screen footprint must fit (up to ``pad``): the skeleton, the body shapes
        and the force arrow. (A ball is drawn but does not steer the framing: it may fly in from
        far away.)"""
        pts = [self.points(which)[k] + offset]
        if self.has_shapes:
            pts.append(self.shape_points(k, which) + offset)
        if which == "perturbed" and self.force_on[k]:
            pts.append(np.stack(self.arrow(k)))
        return np.concatenate(pts)

    def box_centre(self, pts):
        """Centre of the bounding box of ``pts`` in the camera's axes (screen right, depth, up),
        so that the framing turns with the character rather than with the world axes."""
        axes = np.stack([self.right, np.cross(self.right, self.up), self.up])
        proj = np.asarray(pts, float) @ axes.T
        return 0.5 * (proj.min(axis=0) + proj.max(axis=0)) @ axes

    def ground_mesh(self, center, half_size):
        """A checkered ground plane (world-anchored tiles) around ``center``."""
        import pyvista as pv

        n = int(np.ceil(half_size / GROUND_TILE_M))
        a_ax = self.right
        b_ax = np.cross(self.up, a_ax)
        c = center - np.dot(center, self.up) * self.up + self.ground * self.up
        # Snap to the world tile grid so tiles do not slide with the camera.
        ca, cb = np.round(np.dot(c, a_ax) / GROUND_TILE_M), np.round(np.dot(c, b_ax) / GROUND_TILE_M)
        ia, ib = np.meshgrid(np.arange(-n - 1, n + 2) + ca, np.arange(-n - 1, n + 2) + cb, indexing="ij")
        # Clip the tiles to the square of half_size about the centre, so that the far edge (the
        # horizon) sits at the same height in every panel whatever the tile grid's phase.
        ga = np.clip(ia * GROUND_TILE_M, np.dot(c, a_ax) - half_size, np.dot(c, a_ax) + half_size)
        gb = np.clip(ib * GROUND_TILE_M, np.dot(c, b_ax) - half_size, np.dot(c, b_ax) + half_size)
        grid_pts = ga[..., None] * a_ax + gb[..., None] * b_ax + self.ground * self.up
        m = 2 * n + 3
        vid = np.arange(m * m).reshape(m, m)
        quads = np.stack([vid[:-1, :-1], vid[1:, :-1], vid[1:, 1:], vid[:-1, 1:]], -1).reshape(-1, 4)
        mesh = pv.PolyData(grid_pts.reshape(-1, 3), np.hstack([np.full((len(quads), 1), 4), quads]).ravel())
        parity = ((ia[:-1, :-1] + ib[:-1, :-1]).astype(int) % 2).ravel()
        colors = np.where(parity[:, None] == 0, GROUND_COLORS[0], GROUND_COLORS[1])
        mesh.cell_data["rgb"] = (np.asarray(colors) * 255).astype(np.uint8)
        return mesh


def _add_skeleton(pl, geom, color, joint_color, specular=0.25):
    # Flat meshes with our own normals; Phong interpolation makes them look round.
    for mesh, c in ((geom.bones, color), (geom.joints, joint_color)):
        actor = pl.add_mesh(mesh, color=c, smooth_shading=False, specular=specular, specular_power=20)
        actor.prop.interpolation = "phong"


GHOST_DEPTH_M = 0.05


def _ghost_offset(scene):
    """Shift of the ghost along the line of sight: with parallel projection it lands on the same
    pixels, but sits behind the perturbed figure, so only where the two differ does it show."""
    return -GHOST_DEPTH_M * scene.view


def _add_ground(pl, mesh):
    pl.add_mesh(mesh, scalars="rgb", rgb=True, lighting=False, show_scalar_bar=False)


def _set_camera(pl, scene, focal, scale, distance=20.0):
    pl.camera_position = [tuple(focal + distance * scene.view), tuple(focal), tuple(scene.screen_up)]
    pl.camera.parallel_projection = True
    pl.camera.parallel_scale = scale
    pl.camera.clipping_range = (0.1, 2 * distance + 50.0)


def _fit(scene, pts, focal):
    """Half extents (screen right, screen up) of ``pts`` about ``focal``."""
    rel = pts - focal
    return np.abs(rel @ scene.right).max(), np.abs(rel @ scene.screen_up).max()


# ----------------------------------------------------------------------------------------------
# Filmstrip
# ----------------------------------------------------------------------------------------------

def _render_filmstrip(scene: _Scene, out_tmp, frames: int, ghost: bool = True):
    import pyvista as pv

    times = scene.filmstrip_times(frames)
    ks = scene.index_at(times)
    pw, ph = PANEL_SIZE
    aspect = pw / ph
    # Per column focal point: centre of both characters (horizontal), fixed height for all.
    heights = np.concatenate([np.concatenate([scene.extent_points(k, "perturbed"),
                                              scene.extent_points(k, "original")]) for k in ks]) @ scene.up
    z_mid = 0.5 * (scene.ground + heights.max())
    focals = []
    half_w = half_h = 0.0
    for k in ks:
        both = np.concatenate([scene.extent_points(k, "perturbed"), scene.extent_points(k, "original")])
        c = scene.box_centre(both)
        c = c - np.dot(c, scene.up) * scene.up + z_mid * scene.up
        focals.append(c)
        w, h = _fit(scene, both, c)
        foot = c - np.dot(c, scene.up) * scene.up + scene.ground * scene.up
        _, hg = _fit(scene, foot[None], c)
        half_w, half_h = max(half_w, w), max(half_h, h, hg)
    rmax = scene.pad
    scale = 1.12 * max(half_h + rmax, (half_w + rmax) / aspect)

    pl = pv.Plotter(shape=(2, frames), off_screen=True, window_size=(pw * frames, ph * 2), border=False)
    try:
        pl.set_background("white")
        for col, (k, t, c) in enumerate(zip(ks, times, focals)):
            for row, which in enumerate(("original", "perturbed")):
                pl.subplot(row, col)
                pl.set_background("white")
                _add_ground(pl, scene.ground_mesh(c, 3.0 * scale * aspect + 1.0))
                geom = _FigureGeometry(scene).update(k, which)
                if which == "original":
                    geom.add(pl, COLOR_ORIGINAL, COLOR_ORIGINAL_JOINT)
                else:
                    geom.add(pl, COLOR_PERTURBED, COLOR_PERTURBED_JOINT)
                    if ghost:
                        gg = _FigureGeometry(scene).update(k, "original", _ghost_offset(scene))
                        gg.add(pl, COLOR_GHOST, COLOR_GHOST_JOINT, specular=0.0)
                    if scene.force_on[k]:
                        arrow = _ArrowGeometry()
                        arrow.update(*scene.arrow(k))
                        pl.add_mesh(arrow.mesh, color=COLOR_FORCE, smooth_shading=False)
                        pl.add_text(scene.force_label(k), position="lower_right", font_size=9,
                                    color=COLOR_FORCE)
                    if scene.has_ball:
                        pl.add_mesh(pv.Sphere(radius=float(scene.d["ball_radius"]),
                                              center=scene.d["ball_pos"][k]), color=COLOR_BALL)
                pl.add_text(f"t = {scene.time[k]:.2f} s", position="upper_left", font_size=10, color="black")
                if col == 0:
                    label = which if which == "original" or not ghost else "perturbed (pale: original)"
                    pl.add_text(label, position="lower_left", font_size=9, color="black")
                _set_camera(pl, scene, c, scale)
        img = pl.screenshot(return_img=True).copy()
    finally:
        pl.close()
    # Thin separators between panels.
    sep = np.array([190, 190, 190], np.uint8)
    img[ph - 1:ph + 1, :, :3] = sep
    for c in range(1, frames):
        img[:, c * pw - 1:c * pw + 1, :3] = sep
    _write_png(out_tmp, img)
    return img


# ----------------------------------------------------------------------------------------------
# Video
# ----------------------------------------------------------------------------------------------

def video_sample_times(time, fps):
    """Real-time sampling instants of a video of ``time`` at ``fps``."""
    n = int(np.floor((time[-1] - time[0]) * fps + 1e-9)) + 1
    return time[0] + np.arange(n) / fps


def _forking_once(append):
    """``append`` with its first call (where imageio-ffmpeg starts ffmpeg) warning-silenced."""
    started = [False]

    def wrapped(img):
        if started[0]:
            return append(img)
        with _fork_exec_warning_silenced():
            out = append(img)
        started[0] = True
        return out

    return wrapped


@contextlib.contextmanager
def _fork_exec_warning_silenced():
    """Silence JAX's ``os.fork() was called ... JAX is multithreaded`` RuntimeWarning while
    imageio-ffmpeg starts ffmpeg. That start is subprocess.Popen: on Python < 3.12 its C
    fork_exec runs the interpreter's at-fork hooks, where JAX warns; but the child only execs
    ffmpeg (no Python, no JAX runs in it), so the deadlock JAX warns about cannot happen. Only
    that message is filtered, only here."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        yield


def _render_video(scene: _Scene, out_tmp, ext, progress=True, ghost=True):
    import pyvista as pv
    from tqdm import tqdm

    fps = VIDEO_FPS[ext]
    times = video_sample_times(scene.time, fps)
    ks = scene.index_at(times)
    W, H = VIDEO_SIZE
    aspect = W / H
    # Original beside the perturbed one, on the screen's left: shift along -right by the smallest
    # amount that keeps the two (and the arrow) apart in every frame.
    rmax = scene.pad
    gap = 0.35
    shifts = []
    for k in ks:
        a_min = (scene.extent_points(k, "perturbed") @ scene.right).min()
        b_max = (scene.extent_points(k, "original") @ scene.right).max()
        shifts.append(b_max - a_min)
    shift = (max(shifts) + 2 * rmax + gap) * scene.right
    # Camera: follows the (smoothed) centre of the pair; one scale for the whole video.
    centres = []
    for k in ks:
        pts = np.concatenate([scene.extent_points(k, "perturbed"), scene.extent_points(k, "original") - shift])
        centres.append(scene.box_centre(pts))
    centres = np.asarray(centres)
    win = max(1, int(round(fps)))   # ~1 s box filter
    pad = np.pad(centres, ((win // 2, win // 2), (0, 0)), mode="edge")
    kernel = np.ones(win) / win
    smooth = np.stack([np.convolve(pad[:, i], kernel, mode="valid")[: len(ks)] for i in range(3)], 1)
    z_mid = 0.5 * (scene.ground + max(float((np.concatenate([scene.extent_points(k, "perturbed"),
                                                          scene.extent_points(k, "original")]) @ scene.up).max())
                                       for k in np.unique(ks)))
    focals = smooth - (smooth @ scene.up)[:, None] * scene.up + z_mid * scene.up
    half_w = half_h = 0.0
    for k, f in zip(ks, focals):
        pts = np.concatenate([scene.extent_points(k, "perturbed"), scene.extent_points(k, "original") - shift,
                              (f - np.dot(f, scene.up) * scene.up + scene.ground * scene.up)[None]])
        w, h = _fit(scene, pts, f)
        half_w, half_h = max(half_w, w), max(half_h, h)
    scale = 1.1 * max(half_h + rmax, (half_w + rmax) / aspect)

    pl = pv.Plotter(off_screen=True, window_size=(W, H))
    frames = []
    writer = None
    try:
        pl.set_background("white")
        travel = np.ptp(focals @ scene.right) + np.ptp(focals @ np.cross(scene.up, scene.right))
        ground = scene.ground_mesh(focals.mean(axis=0), 3.0 * scale * aspect + travel + 1.0)
        _add_ground(pl, ground)
        g_pert = _FigureGeometry(scene)
        g_orig = _FigureGeometry(scene)
        g_orig.add(pl, COLOR_ORIGINAL_VIDEO, COLOR_ORIGINAL)
        g_ghost = None
        if ghost:
            g_ghost = _FigureGeometry(scene)
            g_ghost.add(pl, COLOR_GHOST, COLOR_GHOST_JOINT, specular=0.0)
        g_pert.add(pl, COLOR_PERTURBED, COLOR_PERTURBED_JOINT)
        arrow = _ArrowGeometry()
        arrow_actor = pl.add_mesh(arrow.mesh, color=COLOR_FORCE, smooth_shading=False)
        ball = None
        if scene.has_ball:
            ball = pv.Sphere(radius=float(scene.d["ball_radius"]), theta_resolution=24, phi_resolution=16)
            ball_dirs = np.asarray(ball.points).copy()
            ball_actor = pl.add_mesh(ball, color=COLOR_BALL, smooth_shading=True)
        pl.add_text("original", position="upper_left", font_size=10, color=COLOR_ORIGINAL_JOINT)
        pl.add_text("perturbed", position="upper_right", font_size=10, color=COLOR_PERTURBED_JOINT)
        clock = pl.add_text("", position="lower_left", font_size=10, color="black")
        ftext = pl.add_text("", position="lower_right", font_size=10, color=COLOR_FORCE)
        if ext == ".mp4":
            import imageio.v2 as iio2

            writer = iio2.get_writer(out_tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                     quality=7, macro_block_size=8, ffmpeg_log_level="error")
            writer.append_data = _forking_once(writer.append_data)
        for i, k in enumerate(tqdm(ks, desc=f"rendering {ext[1:]}", unit="frame", disable=not progress)):
            g_pert.update(k, "perturbed")
            g_orig.update(k, "original", -shift)
            if g_ghost is not None:
                g_ghost.update(k, "original", _ghost_offset(scene))
            on = bool(scene.force_on[k])
            arrow_actor.SetVisibility(on)
            if on:
                arrow.update(*scene.arrow(k))
            ftext.set_text("lower_right", f"force {scene.fmag[k]:.0f} N" if on else "")
            if ball is not None:
                # The ball belongs to the perturbed run: drawn on its (right) half of the frame
                # only, never over the original figure beside it.
                pos = scene.d["ball_pos"][k]
                boundary = 0.5 * ((scene.extent_points(k, "original") - shift) @ scene.right).max() \
                    + 0.5 * (scene.extent_points(k, "perturbed") @ scene.right).min()
                ball_actor.SetVisibility(bool(pos @ scene.right - float(scene.d["ball_radius"]) > boundary))
                ball.points = ball_dirs + pos
            clock.set_text("lower_left", f"t = {scene.time[k]:.2f} s")
            _set_camera(pl, scene, focals[i], scale)
            pl.render()   # screenshot() only renders by itself the first time
            img = pl.screenshot(return_img=True)
            if writer is not None:
                writer.append_data(img)
            else:
                frames.append(img)
        if writer is not None:
            writer.close()
            writer = None
    finally:
        if writer is not None:
            writer.close()
        pl.close()
    if ext == ".gif":
        import imageio.v3 as iio

        iio.imwrite(out_tmp, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    return len(ks)


# ----------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------

def render_run(run_path, out_path, frames: int = 6, progress: bool = True,
               ghost: bool = True, stage=None) -> pathlib.Path:
    """Render a RUN.npz by the extension of ``out_path``.

    ``.png``: a Figure-2 filmstrip, ``frames`` panels per row (top: original motion, bottom:
    perturbed), ``PANEL_SIZE`` pixels each, at instants spread from just before the hit until
    the deviation has mostly decayed; with ``ghost`` the original is also drawn, pale, behind
    the perturbed figure so that small deviations show. ``.mp4`` / ``.gif``: a real-time video (30 / 25 fps) of
    ``VIDEO_SIZE`` pixels with the original (light, on the left) beside the perturbed motion
    (and, with ``ghost``, pale behind it). ``stage``: called with a line of text as each stage
    begins (the CLI's progress lines).
    """
    stage = stage or (lambda text: None)
    out = pathlib.Path(out_path)
    ext = out.suffix.lower()
    if ext not in IMAGE_EXTENSIONS + VIDEO_EXTENSIONS:
        raise RenderError(f"{out}: unknown output extension {out.suffix!r}; "
                          f"use one of {', '.join(IMAGE_EXTENSIONS + VIDEO_EXTENSIONS)}")
    if ext == ".png" and (int(frames) != frames or frames < 1):
        raise RenderError(f"{out}: frames must be a positive integer, got {frames!r}")
    stage(f"loading run {run_path}")
    scene = _Scene(load_run(run_path))
    with atomic_path(out) as tmp:
        if ext == ".png":
            stage(f"rendering a {int(frames)}-panel filmstrip")
            _render_filmstrip(scene, tmp, int(frames), ghost=ghost)
        else:
            n = len(video_sample_times(scene.time, VIDEO_FPS[ext]))
            stage(f"rendering and encoding {n} video frames")
            _render_video(scene, tmp, ext, progress=progress, ghost=ghost)
        stage(f"writing {out}")
    return out


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _json_field(d, key):
    """A JSON string array of a run as a dict, or None (absent or unreadable)."""
    if key not in d:
        return None
    try:
        import json

        value = json.loads(str(d[key]))
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def plot_run(run_path, out_png, n_joints: int = 4) -> pathlib.Path:
    """Matplotlib summary of a run: the RMS joint-angle deviation of the perturbed from the
    unperturbed motion (deg) with the force magnitude on a twin axis, and the ``n_joints`` most
    deflected DOFs against their unperturbed and desired (mocap) values."""
    out = pathlib.Path(out_png)
    if out.suffix.lower() != ".png":
        raise RenderError(f"{out}: unknown output extension {out.suffix!r}; plots are written as .png")
    d = load_run(run_path, _PLOT_FIELDS)
    from matplotlib.figure import Figure  # no pyplot: no GUI backend is ever touched

    t = d["time"]
    dev = np.degrees(_wrap(d["theta"] - d["theta_unperturbed"]))
    rms = np.sqrt(np.mean(dev ** 2, axis=1))
    fmag = np.linalg.norm(d["force_vector"], axis=1)
    names = [str(n) for n in d["dof_names"]]
    n_show = min(n_joints, len(names))
    order = np.argsort(-np.abs(dev).max(axis=0))[:n_show]

    fig = Figure(figsize=(10, 3.2 + 2.4 * int(np.ceil(n_show / 2))), dpi=100, layout="constrained")
    rows = 1 + int(np.ceil(n_show / 2))
    gs = fig.add_gridspec(rows, 2, height_ratios=[1.3] + [1] * (rows - 1))
    ax = fig.add_subplot(gs[0, :])
    ax.plot(t, rms, color="tab:orange", lw=2, label="RMS deviation (perturbed - unperturbed)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("RMS joint-angle deviation (deg)")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.fill_between(t, fmag, color="tab:red", alpha=0.18, lw=0)
    ax2.plot(t, fmag, color="tab:red", lw=1, label="force magnitude")
    ax2.set_ylabel("force (N)", color="tab:red")
    ax2.tick_params(axis="y", colors="tab:red")
    ax2.set_ylim(0, max(fmag.max(), 1.0) * 1.15)
    title = "Deviation from the unperturbed motion"
    if "metrics_json" in d:
        try:
            m = json.loads(str(d["metrics_json"]))
        except ValueError:
            m = {}
        num = lambda k: m.get(k) if isinstance(m.get(k), (int, float)) and not isinstance(m.get(k), bool) else None
        bits = []
        if num("peak_deviation_deg") is not None:
            bits.append(f"peak {num('peak_deviation_deg'):.2f} deg"
                        + (f" at {num('time_of_peak_s'):.2f} s" if num("time_of_peak_s") is not None else ""))
        if num("recovery_time_s") is not None:
            bits.append(f"recovered after {num('recovery_time_s'):.2f} s")
        if num("recovery_threshold_deg") is not None:
            ax.axhline(num("recovery_threshold_deg"), color="0.5", ls=":", lw=1,
                       label=f"recovery threshold ({num('recovery_threshold_deg'):g} deg)")
        if bits:
            title += " (" + ", ".join(bits) + ")"
    ax.set_title(title)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)
    for i, j in enumerate(order):
        a = fig.add_subplot(gs[1 + i // 2, i % 2])
        ref = np.degrees(d["theta_unperturbed"][:, j])
        # Unwrap consistently so curves do not jump at +-180 deg.
        a.plot(t, np.degrees(d["theta_desired"][:, j]), color="0.55", lw=1, ls="--", label="desired (mocap)")
        a.plot(t, ref, color="tab:blue", lw=1.5, label="unperturbed")
        a.plot(t, ref + dev[:, j], color="tab:orange", lw=1.5, label="perturbed")
        a.set_title(f"{names[j]} (max deflection {np.abs(dev[:, j]).max():.1f} deg)", fontsize=9)
        a.set_xlabel("time (s)", fontsize=8)
        a.set_ylabel("angle (deg)", fontsize=8)
        a.tick_params(labelsize=8)
        a.grid(alpha=0.3)
        if i == 0:
            a.legend(fontsize=7)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    return out
