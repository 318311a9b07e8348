"""Convex polyhedra and their exact mass properties (the paper's polyhedral mass model).

For a closed triangle mesh with outward faces, split the solid into signed tetrahedra
(origin, a, b, c), one per face. A tetrahedron's signed volume is ``det[a b c] / 6``; its first
moment is its volume times the centroid ``(a + b + c) / 4``; its second moment
``integral x x^T dV`` is ``vol / 20 (a a^T + b b^T + c c^T + s s^T)`` with ``s = a + b + c``.
Summing gives the exact volume, centre of mass and covariance of the solid; the inertia about
the COM is ``trace(C) I - C`` with C the covariance shifted to the COM (parallel axes).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import ConvexHull, QhullError


@dataclasses.dataclass(frozen=True)
class Polyhedron:
    vertices: np.ndarray  # (V,3) metres
    faces: np.ndarray  # (F,3) triangles, counter-clockwise seen from outside


def convex_hull(points) -> Polyhedron:
    """Convex hull with every triangle oriented outward."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 4:
        raise ValueError(f"convex hull needs at least 4 non-coplanar points, got {len(pts)}")
    try:
        hull = ConvexHull(pts)
    except QhullError as e:
        raise ValueError(f"degenerate point set (flat or collinear): {str(e).splitlines()[0]}") from None
    faces = hull.simplices.copy()
    a, b, c = pts[faces[:, 0]], pts[faces[:, 1]], pts[faces[:, 2]]
    normal = np.cross(b - a, c - a)
    # qhull's facet normals point outward; flip triangles whose winding disagrees.
    flip = np.einsum("ij,ij->i", normal, hull.equations[:, :3]) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return Polyhedron(pts, faces)


def mass_properties(poly: Polyhedron, density: float = 1000.0):
    """(mass, centre of mass (3,), inertia about the COM (3,3)) of a closed outward mesh."""
    v = poly.vertices[poly.faces]  # (F,3,3)
    a, b, c = v[:, 0], v[:, 1], v[:, 2]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    volume = vol.sum()
    if not volume > 0:
        raise ValueError(f"mesh volume is {volume:.3g}: faces must be closed and oriented outward")
    s = a + b + c
    com = (vol[:, None] * s).sum(0) / (4.0 * volume)
    second = np.einsum("f,fi,fj->ij", vol, a, a) + np.einsum("f,fi,fj->ij", vol, b, b)
    second += np.einsum("f,fi,fj->ij", vol, c, c) + np.einsum("f,fi,fj->ij", vol, s, s)
    cov = density * (second / 20.0 - volume * np.outer(com, com))
    inertia = np.trace(cov) * np.eye(3) - cov
    return float(density * volume), com, 0.5 * (inertia + inertia.T)


def prism(start, end, radius: float, sides: int = 8) -> np.ndarray:
    """Vertices (2*sides, 3) of a regular prism of circumradius ``radius`` around start->end."""
    start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
    axis = end - start
    length = np.linalg.norm(axis)
    if not length > 0:
        raise ValueError("prism needs start != end")
    axis = axis / length
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    ang = 2.0 * np.pi * np.arange(sides) / sides
    ring = radius * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w)
    return np.concatenate([start + ring, end + ring])


def segment_hull(segments, sides: int = 8) -> Polyhedron:
    """Convex hull of the prisms around several (start, end, radius) bone segments."""
    return convex_hull(np.concatenate([prism(s, e, r, sides) for s, e, r in segments]))


def box(half_extents) -> Polyhedron:
    """Axis-aligned box centred at the origin."""
    h = np.asarray(half_extents, np.float64)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    return convex_hull(corners * h)
