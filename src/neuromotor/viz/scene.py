"""What a run shows, for drawing: both figures over time, the hit, the camera's axes and the ground.

:class:`Scene` holds the arrays read from a RUN.npz and answers the questions the filmstrip and
the video ask: where the body shapes are at a sample, where the force arrow goes (its tip 1 cm
outside the body surface at the point of application, ``|F| / FORCE_SCALE_N_PER_M`` long) and
the balance assist's (from the pelvis's COM, at the same scale), when
the character is hit, which instants a filmstrip shows, and where the ground lies.
"""

from __future__ import annotations

import numpy as np

from neuromotor.io.runfile import json_field
from neuromotor.model.facing import facing_direction, horizontal, unit
from neuromotor.viz.camera import camera_view
from neuromotor.viz.geometry import quat_matrices
from neuromotor.viz.style import (
    DETAIL_RADIUS_M,
    FORCE_SCALE_N_PER_M,
    FORCE_VISIBLE_FRACTION,
    GROUND_COLORS,
    GROUND_TILE_M,
)

_NO_OFFSET = np.zeros(3)  # default offset, shared: never written to


def _on(mag):
    """Samples where a magnitude exceeds ``FORCE_VISIBLE_FRACTION`` of its peak."""
    return mag > FORCE_VISIBLE_FRACTION * mag.max() if mag.max() > 0 else np.zeros(len(mag), bool)


class Scene:
    """A run's arrays ``d`` (from :func:`neuromotor.viz.data.load_run`) prepared for drawing."""

    def __init__(self, d):
        self.d = d
        self.time = d["time"].astype(float)
        self.P = d["skeleton_points"].astype(float)
        self.U = d["skeleton_points_unperturbed"].astype(float)
        self.up_axis = int(d.get("up_axis", 1))
        self.up = np.eye(3)[self.up_axis]
        self.F = d["force_vector"].astype(float)
        self.Fo = d["force_origin"].astype(float)
        self.fmag = np.linalg.norm(self.F, axis=1)
        self.force_on = _on(self.fmag)
        self._init_shapes()
        self.pad = 1.25 * float(self.capsule_radii.max()) if len(self.capsule_radii) else 0.0
        self._init_camera()
        self._init_tilt()
        self.ground = self._lowest_point() if not self.ground_moves else float(d["ground_height"])
        self.has_ball = "ball_pos" in d
        self._init_assist()
        self._init_hit()
        self.metrics = json_field(d, "metrics_json")
        self.provenance = json_field(d, "provenance_json")

    def _init_shapes(self):
        """Body shapes (world = body_pos + R(body_quat) @ v) and the capsules drawn besides them
        (detail bones), or, without shapes, capsules for every bone."""
        d = self.d
        edges, radii = d["skeleton_edges"].astype(int), d["skeleton_radii"].astype(float)
        self.has_shapes = "shape_vertices" in d and len(d["shape_vertices"]) > 0 and len(d["shape_faces"]) > 0
        if not self.has_shapes:
            self.capsule_edges, self.capsule_radii = edges, radii
            return
        self.shape_v = d["shape_vertices"].astype(float)
        self.shape_b = d["shape_body"].astype(int)
        self.body_pos = {"perturbed": d["body_pos"].astype(float), "original": d["body_pos_unperturbed"].astype(float)}
        self.body_rot = {
            "perturbed": quat_matrices(d["body_quat"]),
            "original": quat_matrices(d["body_quat_unperturbed"]),
        }
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

    def _init_camera(self):
        """The hit's horizontal direction (at its peak), the facing direction, and the camera's
        axes: a three-quarter front view."""
        fmag = self.fmag
        self.hit_dir = horizontal(self.F[int(np.argmax(fmag))], self.up) if fmag.max() > 0 else None
        self.facing = facing_direction(self.U, self.d["skeleton_edges"].astype(int), self.up_axis, self.d.get("facing"))
        self.view = camera_view(self.facing, self.up, self.hit_dir)  # from the scene to the camera
        self.right = unit(np.cross(self.up, self.view), np.roll(self.up, 2))
        self.screen_up = np.cross(self.view, self.right)
        self.screen_up /= np.linalg.norm(self.screen_up)

    def _init_tilt(self):
        """A ground that moves under a free root: a tilt (RUN.npz ``ground_turn``, ``ground_pivot``:
        its rotation per sample (T, 3, 3) and pivot) and a platform's translation (``base_offset``
        (T, 3) of a free-root run on a ground); None: still. A moving ground is the run's
        ``ground_height`` moved so, and drawn so: the lowest point of such a run is not the ground."""
        d = self.d
        self.ground_turn, self.ground_pivot, self.ground_shift = None, None, None
        if "ground_turn" in d:
            self.ground_turn = quat_matrices(d["ground_turn"])
            self.ground_pivot = np.asarray(d["ground_pivot"], float)
        root = (json_field(d, "provenance_json") or {}).get("root")
        if "base_offset" in d and "ground_height" in d and root == "free":  # a driven root's is the root's own
            self.ground_shift = np.asarray(d["base_offset"], float)

    @property
    def ground_moves(self) -> bool:
        return self.ground_turn is not None or self.ground_shift is not None

    def moved(self, pts, k):
        """Points of the still, level ground where the moving ground has them at sample ``k``:
        turned about the pivot, then carried by the platform (``pivot + D_k + R_k (p - pivot)``, as
        the step has it); unchanged on a still ground or with ``k`` None."""
        if not self.ground_moves or k is None:
            return pts
        pts = np.asarray(pts, float)
        if self.ground_turn is not None:
            pts = self.ground_pivot + (pts - self.ground_pivot) @ self.ground_turn[k].T
        if self.ground_shift is not None:
            pts = pts + self.ground_shift[k]
        return pts

    def _lowest_point(self) -> float:
        """Height of the ground: touching the lowest surface of either figure (or the ball) over
        the whole run."""
        low = np.inf
        for which in ("perturbed", "original"):
            if self.has_shapes:
                pos, rot = self.body_pos[which], self.body_rot[which]
                h = pos[:, self.shape_b] @ self.up + np.einsum(
                    "tvj,vj->tv", rot[:, self.shape_b, self.up_axis, :], self.shape_v
                )
                low = min(low, float(h.min()))
            if len(self.capsule_edges):
                e, r = self.capsule_edges, self.capsule_radii
                h = self.points(which) @ self.up  # (T, P)
                low = min(low, float((np.minimum(h[:, e[:, 0]], h[:, e[:, 1]]) - r).min()))
        if "ball_pos" in self.d:
            hb = self.d["ball_pos"] @ self.up - float(self.d["ball_radius"])
            low = min(low, float(hb.min()))
        return low

    def _init_assist(self):
        """The balance assist's virtual force on the pelvis (RUN.npz ``assist_force`` at
        ``assist_point``; off: never drawn): help, not physics, drawn in its own colour so that
        nobody takes it for either."""
        d = self.d
        n = len(self.time)
        self.assist_force = np.asarray(d["assist_force"], float) if "assist_force" in d else np.zeros((n, 3))
        self.assist_point = np.asarray(d["assist_point"], float) if "assist_point" in d else np.zeros((n, 3))
        self.assist_mag = np.linalg.norm(self.assist_force, axis=1)
        self.assist_on = _on(self.assist_mag)

    def assist_arrow(self, k):
        """(tail, tip) of the assist's arrow at sample k: from the pelvis's COM along the force,
        ``|F| / FORCE_SCALE_N_PER_M`` long (the browser viewer's arrow)."""
        tail = self.assist_point[k]
        return tail, tail + self.assist_force[k] / FORCE_SCALE_N_PER_M

    def assist_label(self, k):
        return f"assist {self.assist_mag[k]:.0f} N (not physics)"

    def _init_hit(self):
        """What hits the character over time (N): the applied force, or the ball's contact force."""
        d, hit = self.d, self.fmag.copy()
        if "contact_force" in d and np.ndim(d["contact_force"]) == 3 and len(d["contact_force"]) == len(hit):
            hit = np.maximum(hit, np.linalg.norm(np.asarray(d["contact_force"], float).sum(axis=1), axis=1))
        self.hit_mag = hit
        self.hit_on = _on(hit)

    def force_label(self, k):
        """Label of the force drawn at sample k: the configured peak magnitude of the pulse acting
        then (from the run's provenance), else the largest sampled |F| of the hit, not the
        sampled value at k (a half-sine's samples are below its peak)."""
        t = float(self.time[k])
        for p in (self.provenance or {}).get("perturbations", []):
            # physics.perturbation.PLATFORM_KINDS (viz reads files, not the physics): no force drawn
            if p.get("kind") in ("base", "tilt"):
                continue
            try:
                start, dur, mag = float(p["start"]), float(p["duration"]), float(p["magnitude"])
            except (KeyError, TypeError, ValueError):
                continue
            h = float(self.time[1] - self.time[0]) if len(self.time) > 1 else dur
            impulse = p.get("kind") == "impulse"
            # An impulse acts in the one step centred on its start: the sample may precede it.
            if start - (h if impulse else 0.0) - 1e-9 <= t <= start + max(dur, h):
                return f"{mag:.0f} {'N s' if impulse else 'N'}"
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
        u = unit(f, [1.0, 0.0, 0.0])
        tip = o - u * self.surface_depth(k)
        return tip - f / FORCE_SCALE_N_PER_M, tip

    def surface_depth(self, k):
        """How far back from the application point along the force the body's surface lies, plus
        1 cm: where the ray backwards leaves the (convex) body shapes containing the point, or,
        without shapes, the nearest capsule's radius less the point's distance from its axis."""
        o = self.Fo[k]
        u = unit(self.F[k], [1.0, 0.0, 0.0])
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
        t_hit = float(t[win[0] + int(np.argmax(self.hit_mag[win[0] : win[1] + 1]))])
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
        t_start = max(t[0], t_on - span / (n - 1))  # one panel before the hit
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

    def extent_points(self, k, which, offset=_NO_OFFSET):
        """Points whose screen footprint must fit (up to ``pad``): the skeleton, the body shapes,
        the force arrow and the assist's. (A ball is drawn but does not steer the framing: it may
        fly in from far away.)"""
        pts = [self.points(which)[k] + offset]
        if self.has_shapes:
            pts.append(self.shape_points(k, which) + offset)
        if which == "perturbed" and self.force_on[k]:
            pts.append(np.stack(self.arrow(k)))
        if which == "perturbed" and self.assist_on[k]:
            pts.append(np.stack(self.assist_arrow(k)))
        return np.concatenate(pts)

    def box_centre(self, pts):
        """Centre of the bounding box of ``pts`` in the camera's axes (screen right, depth, up),
        so that the framing turns with the character rather than with the world axes."""
        axes = np.stack([self.right, np.cross(self.right, self.up), self.up])
        proj = np.asarray(pts, float) @ axes.T
        return 0.5 * (proj.min(axis=0) + proj.max(axis=0)) @ axes

    def ground_mesh(self, center, half_size, k=None):
        """A checkered ground plane (world-anchored tiles) around ``center``; a moving ground
        (a tilt, a platform) as it is at sample ``k``."""
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
        mesh = pv.PolyData(
            self.moved(grid_pts.reshape(-1, 3), k), np.hstack([np.full((len(quads), 1), 4), quads]).ravel()
        )
        parity = ((ia[:-1, :-1] + ib[:-1, :-1]).astype(int) % 2).ravel()
        colors = np.where(parity[:, None] == 0, GROUND_COLORS[0], GROUND_COLORS[1])
        mesh.cell_data["rgb"] = (np.asarray(colors) * 255).astype(np.uint8)
        return mesh
