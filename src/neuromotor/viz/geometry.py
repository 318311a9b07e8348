"""Meshes of fixed topology whose points are recomputed per frame: capsule bones and joint
spheres, the force arrow, the bodies' polyhedra, and one figure made of them.

No actor is rebuilt per frame: each mesh keeps its cells, and ``update`` moves its points (and
normals, computed once in the body frames and turned with their bodies).
"""

from __future__ import annotations

import numpy as np

from neuromotor.model.facing import unit

_NO_OFFSET = np.zeros(3)  # default offset, shared: never written to


def poly(points, faces, nverts):
    import pyvista as pv

    faces = np.asarray(faces).reshape(-1, nverts)
    return pv.PolyData(points, np.hstack([np.full((len(faces), 1), nverts), faces]).ravel())


class SkeletonGeometry:
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
        self.bones = poly(np.zeros((cap_base + 2 * E * nv, 3)), np.concatenate([cyl_tris, spheres(2 * E, cap_base)]), 3)
        self.cap_normals = np.tile(self.sph_dirs, (2 * E, 1))
        J = len(self.joint_idx)
        self.joints = poly(np.zeros((max(J, 1) * nv, 3)), spheres(max(J, 1), 0), 3)
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
        ring = self.radii[:, None, None] * normal  # (E, S, 3)
        cyl = np.concatenate([a[:, None] + ring, b[:, None] + ring], axis=1)  # (E, 2S, 3)
        ends = np.concatenate([a, b])  # (2E, 3)
        rr = np.concatenate([self.radii, self.radii])
        caps = ends[:, None] + rr[:, None, None] * self.sph_dirs[None]
        self.bones.points = np.concatenate([cyl.reshape(-1, 3), caps.reshape(-1, 3)])
        self.bones.point_data["Normals"] = np.concatenate(
            [np.concatenate([normal, normal], axis=1).reshape(-1, 3), self.cap_normals]
        )
        self.bones.point_data.active_normals_name = "Normals"
        if len(self.joint_idx):
            c = points[self.joint_idx]
            self.joints.points = (c[:, None] + self.joint_radii[:, None, None] * self.sph_dirs[None]).reshape(-1, 3)
        else:  # a single chain of two points: hide the placeholder joint inside the first point
            self.joints.points = np.repeat(points[:1], len(self.sph_dirs), axis=0)


class ArrowGeometry:
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
        quads = [
            np.stack([j, jn, S + jn, S + j], 1),  # shaft side
            np.stack([S + j, S + jn, 2 * S + jn, 2 * S + j], 1),
        ]  # head base annulus
        tris = [
            np.stack([2 * S + j, 2 * S + jn, np.full(S, 3 * S)], 1),  # cone
            np.stack([jn, j, np.full(S, 3 * S + 1)], 1),
        ]  # tail cap
        cells = [np.hstack([np.full((S, 1), 4), q]) for q in quads]
        cells += [np.hstack([np.full((S, 1), 3), t]) for t in tris]
        self.mesh = pv.PolyData(np.zeros((3 * S + 2, 3)), np.concatenate([c.ravel() for c in cells]))
        self.update(np.zeros(3), np.array([1.0, 0.0, 0.0]))

    def update(self, tail, tip):
        tail, tip = np.asarray(tail, float), np.asarray(tip, float)
        d = tip - tail
        L = max(np.linalg.norm(d), 1e-6)
        u = unit(d, [1.0, 0.0, 0.0])
        helper = [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]
        e1 = unit(np.cross(u, helper), [0.0, 1.0, 0.0])
        e2 = np.cross(u, e1)
        lh = min(self.lh, 0.5 * L)
        ring = self.cs[:, None] * e1 + self.sn[:, None] * e2
        head_base = tip - lh * u
        pts = np.concatenate(
            [tail + self.rs * ring, head_base + self.rs * ring, head_base + self.rh * ring, tip[None], tail[None]]
        )
        self.mesh.points = pts


def quat_matrices(q):
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in w x y z order (normalised)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


class BodyGeometry:
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
        base = poly(vertices, np.asarray(faces, int), 3)
        split = base.compute_normals(
            cell_normals=False,
            split_vertices=True,
            consistent_normals=False,
            auto_orient_normals=False,
            feature_angle=feature_angle,
        )
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


class FigureGeometry:
    """One figure as drawn: the bodies' polyhedra (when the run has them) plus thin capsules for
    the bones that carry no body (fingers, toes, face), or, for a run without shapes, capsules
    for every bone."""

    def __init__(self, scene):
        self.scene = scene
        self.bodies = None
        if scene.has_shapes:
            d = scene.d
            self.bodies = BodyGeometry(d["shape_vertices"], d["shape_faces"], d["shape_body"])
        self.capsules = None
        if len(scene.capsule_edges):
            self.capsules = SkeletonGeometry(scene.capsule_edges, scene.capsule_radii, scene.P.shape[1])

    def update(self, k, which, offset=_NO_OFFSET):
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
            actor = pl.add_mesh(
                self.bodies.mesh, color=color, smooth_shading=False, specular=specular, specular_power=20
            )
            actor.prop.interpolation = "phong"
        if self.capsules is not None:
            # Detail bones beside bodies are drawn in the darker joint colour.
            add_skeleton(
                pl, self.capsules, joint_color if self.bodies is not None else color, joint_color, specular=specular
            )


def add_skeleton(pl, geom, color, joint_color, specular=0.25):
    # Flat meshes with our own normals; Phong interpolation makes them look round.
    for mesh, c in ((geom.bones, color), (geom.joints, joint_color)):
        actor = pl.add_mesh(mesh, color=c, smooth_shading=False, specular=specular, specular_power=20)
        actor.prop.interpolation = "phong"


def add_ground(pl, mesh):
    pl.add_mesh(mesh, scalars="rgb", rgb=True, lighting=False, show_scalar_bar=False)
