"""Polyhedral body shapes and their exact mass properties.

Yin, Cline & Pai (2003) model every body segment as a polyhedron of uniform density (water,
1000 kg/m^3). This module builds such shapes (convex hulls of regular prisms wrapped around the
bones) and integrates their mass, centre of mass and inertia tensor in closed form.

Formulas
--------
Let the solid be bounded by a closed triangle mesh whose triangles are wound counter-clockwise
seen from outside. Pick a reference point ``p`` (we use the mean vertex, which only improves
round-off; any point gives the same answer). Every triangle ``(a, b, c)``, written relative to
``p``, spans a tetrahedron ``(0, a, b, c)`` with *signed* volume

    v = a . (b x c) / 6 = det[a b c] / 6,

positive when the triangle faces away from ``p`` and negative otherwise. By the divergence
theorem the signed tetrahedra cancel outside the solid and add up to exactly one cover of it,
so any integral of a polynomial over the solid is the sum of the same integral over the signed
tetrahedra. For a tetrahedron with one vertex at the origin and the others at a, b, c:

    volume           V_t = v
    first moment     integral x dV   = v (a + b + c) / 4          (volume times centroid)
    second moment    integral x x^T dV = v / 20 (a a^T + b b^T + c c^T + s s^T),  s = a + b + c

(the second-moment formula is the covariance of a uniform tetrahedron: for vertices w_0..w_3 it
is V/20 (sum_k w_k w_k^T + (sum_k w_k)(sum_k w_k)^T), and w_0 = 0 here). Summing over faces gives
the volume V, the first moment S (centre of mass c = p + S / V) and the second moment
C_p = integral (x - p)(x - p)^T dV. Shifting to the centre of mass (parallel axis theorem for the
second moment) gives C = C_p - V d d^T with d = c - p, and the inertia tensor about the centre of
mass at density rho is

    I = rho (trace(C) E - C),        E the 3x3 identity,

which is symmetric and positive definite for any solid with non-zero volume. Mass is rho V.

A mesh whose faces all point inward yields V < 0 and is rejected; so is a mesh that is not
closed, detected by the identity  sum over faces of  integral x n^T dA = V E  (divergence theorem
applied to x_i e_j), which fails for holes and for individually flipped triangles.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import ConvexHull, QhullError

__all__ = ["Polyhedron", "convex_hull", "mass_properties", "prism", "segment_hull", "box", "ellipse_ring"]

# Relative tolerance of the closedness identity (round-off is ~1e-16 of the scale used).
_CLOSED_RTOL = 1e-8
# A hull thinner than this fraction of its bounding box cube is treated as flat.
_FLAT_RTOL = 1e-12


@dataclasses.dataclass(frozen=True, eq=False)
class Polyhedron:
    """A closed triangle mesh: ``vertices`` (V,3) float64 in metres, ``faces`` (F,3) int64
    vertex indices, each triangle counter-clockwise seen from outside (outward normals).

    Both arrays are stored as read-only copies.
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self):
        v = np.array(self.vertices, dtype=np.float64)
        f = np.array(self.faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3) (triangles), got {f.shape}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError(f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        if not np.all(np.isfinite(v)):
            raise ValueError("vertices must be finite")
        v.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)


def convex_hull(points) -> Polyhedron:
    """Convex hull of ``points`` (N,3) as a :class:`Polyhedron` with every triangle oriented
    outward. Only the hull's extreme points are kept as vertices.

    Raises ``ValueError`` when the points do not span a volume (fewer than 4 points, or all on a
    plane or a line) or are not finite.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"convex_hull expects points of shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("convex_hull: points must be finite (got NaN or inf)")
    if len(pts) < 4:
        raise ValueError(f"convex_hull: degenerate input, need at least 4 non-coplanar points, got {len(pts)}")
    extent = float(np.max(pts.max(0) - pts.min(0)))
    try:
        hull = ConvexHull(pts)
    except QhullError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(
            "convex_hull: degenerate input, the points are coplanar or collinear (they need 4 "
            f"non-coplanar points to enclose a volume); qhull said: {first}"
        ) from None
    if not hull.volume > _FLAT_RTOL * extent**3:
        raise ValueError(
            f"convex_hull: degenerate input, the hull is flat (volume {hull.volume:.3g} for an "
            f"extent of {extent:.3g}); the points must not be (nearly) coplanar"
        )

    faces = np.array(hull.simplices, dtype=np.int64)
    a, b, c = pts[faces[:, 0]], pts[faces[:, 1]], pts[faces[:, 2]]
    winding = np.cross(b - a, c - a)
    # qhull's facet equations carry outward unit normals; its simplices' vertex order is arbitrary.
    inward = np.einsum("ij,ij->i", winding, hull.equations[:, :3]) < 0.0
    faces[inward] = faces[inward][:, ::-1]

    # Keep only the vertices used by the hull, re-indexed compactly in order of first use.
    used = np.unique(faces)
    remap = np.full(len(pts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return Polyhedron(pts[used], remap[faces])


def mass_properties(poly: Polyhedron, density: float = 1000.0) -> tuple[float, np.ndarray, np.ndarray]:
    """Exact ``(mass, centre of mass (3,), inertia tensor about the COM (3,3))`` of the uniform
    solid bounded by ``poly`` (a closed, outward-oriented triangle mesh; convex or not).

    Raises ``ValueError`` for a non-positive density, a mesh that is not closed (or has some
    triangles flipped), and a mesh with non-positive volume (faces oriented inward).
    """
    density = float(density)
    if not (np.isfinite(density) and density > 0.0):
        raise ValueError(f"density must be positive and finite, got {density}")
    if len(poly.faces) == 0:
        raise ValueError("mass_properties: the mesh has no faces")

    ref = poly.vertices[np.unique(poly.faces)].mean(0)
    tri = poly.vertices[poly.faces] - ref  # (F, 3 corners, 3 coords)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    vol6 = np.einsum("ij,ij->i", a, np.cross(b, c))  # 6 x signed tetra volumes
    volume = vol6.sum() / 6.0

    # Closedness: sum over faces of (area-weighted centroid) (x) (area vector) must equal V E.
    area_vec = 0.5 * np.cross(b - a, c - a)
    flux = np.einsum("fi,fj->ij", (a + b + c) / 3.0, area_vec)
    scale = np.max(np.abs(tri)) * np.linalg.norm(area_vec, axis=1).sum()
    if not np.all(np.abs(flux - volume * np.eye(3)) <= _CLOSED_RTOL * scale):
        raise ValueError(
            "mass_properties: the mesh is not closed or its triangles are not consistently "
            "oriented (the divergence theorem check sum x n^T dA = V I fails)"
        )
    if not volume > 0.0:
        raise ValueError(
            f"mass_properties: the mesh encloses a non-positive volume ({volume:.3g} m^3); "
            "its faces must be oriented outward (counter-clockwise seen from outside)"
        )

    s = a + b + c
    first = np.einsum("f,fi->i", vol6, s) / 24.0  # sum v (a+b+c)/4, v = vol6/6
    d = first / volume  # centre of mass relative to ref
    w = vol6 / 120.0  # v / 20
    second = (
        np.einsum("f,fi,fj->ij", w, a, a)
        + np.einsum("f,fi,fj->ij", w, b, b)
        + np.einsum("f,fi,fj->ij", w, c, c)
        + np.einsum("f,fi,fj->ij", w, s, s)
    )
    cov = second - volume * np.outer(d, d)  # second moment about the COM (parallel axes)
    cov = 0.5 * (cov + cov.T)
    inertia = density * (np.trace(cov) * np.eye(3) - cov)
    return float(density * volume), ref + d, inertia


def prism(start, end, radius: float, sides: int = 8) -> np.ndarray:
    """Vertices (2*sides, 3) of a right regular ``sides``-gon prism of circumradius ``radius``
    whose axis is the segment start -> end: first the ring around ``start``, then the matching
    ring around ``end``. Works for any axis direction.
    """
    start = np.asarray(start, dtype=np.float64).reshape(3)
    end = np.asarray(end, dtype=np.float64).reshape(3)
    radius = float(radius)
    sides = int(sides)
    if sides < 3:
        raise ValueError(f"prism needs at least 3 sides, got {sides}")
    if not (np.isfinite(radius) and radius > 0.0):
        raise ValueError(f"prism radius must be positive and finite, got {radius}")
    axis = end - start
    length = float(np.linalg.norm(axis))
    if not (np.isfinite(length) and length > 0.0):
        raise ValueError(f"prism needs distinct finite end points, got {start} and {end}")
    axis /= length
    # The coordinate axis least aligned with the prism axis is never (nearly) parallel to it.
    helper = np.zeros(3)
    helper[np.argmin(np.abs(axis))] = 1.0
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)  # (u, w, axis) is right-handed and orthonormal
    angle = 2.0 * np.pi * np.arange(sides) / sides
    ring = radius * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * w)
    return np.concatenate([start + ring, end + ring])


def segment_hull(segments, sides: int = 8) -> Polyhedron:
    """One convex polyhedron wrapping several bone segments: the convex hull of the vertices of
    every segment's prism. ``segments`` is an iterable of ``(start (3,), end (3,), radius)``.
    """
    clouds = [prism(start, end, radius, sides) for start, end, radius in segments]
    if not clouds:
        raise ValueError("segment_hull needs at least one (start, end, radius) segment")
    return convex_hull(np.concatenate(clouds))


def box(half_extents) -> Polyhedron:
    """Axis-aligned box centred at the origin with the given half extents (3,) (or one scalar
    for a cube), as 8 vertices and 12 outward triangles."""
    h = np.broadcast_to(np.asarray(half_extents, dtype=np.float64), (3,))
    if not np.all(np.isfinite(h) & (h > 0.0)):
        raise ValueError(f"box half extents must be positive and finite, got {h}")
    # Vertex k has coordinate signs from its bits: x from bit 0, y from bit 1, z from bit 2.
    signs = np.array([[(k >> i & 1) * 2 - 1 for i in range(3)] for k in range(8)], np.float64)
    faces = np.array(
        [
            [0, 2, 3],
            [0, 3, 1],  # z = -h  (normal -z)
            [4, 5, 7],
            [4, 7, 6],  # z = +h  (normal +z)
            [0, 1, 5],
            [0, 5, 4],  # y = -h  (normal -y)
            [2, 6, 7],
            [2, 7, 3],  # y = +h  (normal +y)
            [0, 4, 6],
            [0, 6, 2],  # x = -h  (normal -x)
            [1, 3, 7],
            [1, 7, 5],  # x = +h  (normal +x)
        ],
        dtype=np.int64,
    )
    return Polyhedron(signs * h, faces)


def ellipse_ring(center, u, v, a: float, b: float, sides: int = 10) -> np.ndarray:
    """Vertices (sides, 3) of a polygon inscribed in the ellipse ``center + a cos(t) u + b sin(t) v``
    (``u``, ``v`` orthonormal). Convex hulls of such rings make the tapered and flattened body
    shapes of :mod:`neuromotor.model.massmodel`."""
    angle = 2.0 * np.pi * np.arange(int(sides)) / int(sides)
    return (
        np.asarray(center, np.float64)
        + a * np.cos(angle)[:, None] * np.asarray(u, np.float64)
        + b * np.sin(angle)[:, None] * np.asarray(v, np.float64)
    )
