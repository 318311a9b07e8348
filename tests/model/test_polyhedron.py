"""Polyhedral mass model: exact mass properties checked against closed forms.

Every expected value below comes from an independent closed form (or a 1-D quadrature), never
from the module under test.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate
from scipy.spatial.transform import Rotation

from neuromotor.model import polyhedron as P

RTOL = 1e-12


def rel_err(actual, expected):
    actual, expected = np.asarray(actual, float), np.asarray(expected, float)
    return np.max(np.abs(actual - expected)) / max(np.max(np.abs(expected)), 1e-300)


def box_inertia(mass, a, b, c):
    """Solid box with full edge lengths a, b, c about its centre: m/12 diag(b²+c², a²+c², a²+b²)."""
    return mass / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])


def shift_inertia(inertia, mass, offset):
    """Parallel axis theorem: inertia about a point at -offset from the COM (offset = com - point)."""
    d = np.asarray(offset, float)
    return inertia + mass * (d @ d * np.eye(3) - np.outer(d, d))


def transformed(poly, rot, shift):
    return P.Polyhedron(poly.vertices @ rot.T + shift, poly.faces)


def assert_outward(poly):
    """Every triangle's normal points away from the (interior) vertex mean: valid for convex meshes."""
    tri = poly.vertices[poly.faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centre = poly.vertices.mean(0)
    assert np.all(np.einsum("ij,ij->i", normal, tri.mean(1) - centre) > 0)


def assert_valid_inertia(inertia, rtol=1e-10):
    np.testing.assert_array_equal(inertia, inertia.T)
    lam = np.linalg.eigvalsh(inertia)
    assert lam[0] > 0, lam
    # Principal moments of a rigid body satisfy the triangle inequalities I1 + I2 >= I3.
    assert lam[0] + lam[1] >= lam[2] * (1 - rtol), lam


# ----------------------------------------------------------------------------- boxes


def test_unit_cube():
    for cube in (P.box([0.5, 0.5, 0.5]), P.convex_hull(np.array(np.meshgrid([0, 1], [0, 1], [0, 1])).reshape(3, -1).T)):
        assert_outward(cube)
        m, com, inertia = P.mass_properties(cube)
        assert m == pytest.approx(1000.0, rel=RTOL)
        expected_com = cube.vertices.min(0) + 0.5
        assert np.max(np.abs(com - expected_com)) < 1e-14
        assert rel_err(inertia, 1000.0 / 6.0 * np.eye(3)) < RTOL


@pytest.mark.parametrize("a,b,c,rho", [(1.0, 2.0, 3.0, 1.0), (0.1, 0.35, 0.02, 1000.0), (7.0, 0.5, 2.5, 19.3)])
def test_box_closed_form(a, b, c, rho):
    m_expected = rho * a * b * c
    for poly in (P.box([a / 2, b / 2, c / 2]), P.convex_hull(P.box([a / 2, b / 2, c / 2]).vertices)):
        assert_outward(poly)
        m, com, inertia = P.mass_properties(poly, rho)
        assert abs(m - m_expected) <= RTOL * m_expected
        assert np.max(np.abs(com)) <= 1e-15 * max(a, b, c)
        assert rel_err(inertia, box_inertia(m_expected, a, b, c)) < RTOL


def test_box_translated_and_rotated():
    a, b, c, rho = 0.4, 1.3, 0.7, 1000.0
    m0 = rho * a * b * c
    i0 = box_inertia(m0, a, b, c)
    rng = np.random.default_rng(0)
    for rot in Rotation.random(5, random_state=1).as_matrix():
        shift = rng.uniform(-3, 3, 3)
        base = P.box([a / 2, b / 2, c / 2])
        for poly in (transformed(base, rot, shift), P.convex_hull(base.vertices @ rot.T + shift)):
            m, com, inertia = P.mass_properties(poly, rho)
            assert abs(m - m0) <= RTOL * m0
            assert np.max(np.abs(com - shift)) <= 1e-14 * np.max(np.abs(shift)) * 10
            assert rel_err(inertia, rot @ i0 @ rot.T) < RTOL


def test_box_inertia_is_not_about_origin():
    """An off-centre box reports inertia about its COM, not about the origin."""
    shift = np.array([2.0, 0.0, 0.0])
    m, com, inertia = P.mass_properties(transformed(P.box([0.5, 0.5, 0.5]), np.eye(3), shift), 1.0)
    np.testing.assert_allclose(com, shift, atol=1e-14)
    assert rel_err(inertia, np.eye(3) / 6.0) < RTOL
    assert rel_err(shift_inertia(inertia, m, shift), np.diag([1 / 6, 1 / 6 + 4, 1 / 6 + 4])) < RTOL


# ----------------------------------------------------------------------------- prisms


def right_triangular_prism(a, b, length):
    """Legs a along x and b along y (right angle at the origin), extruded over z in [0, length]."""
    v = np.array([[0, 0, 0], [a, 0, 0], [0, b, 0], [0, 0, length], [a, 0, length], [0, b, length]], float)
    faces = [
        [0, 2, 1], [3, 4, 5],  # bottom (-z), top (+z)
        [0, 1, 4], [0, 4, 3],  # y = 0 wall (-y)
        [0, 3, 5], [0, 5, 2],  # x = 0 wall (-x)
        [1, 2, 5], [1, 5, 4],  # hypotenuse wall
    ]
    return P.Polyhedron(v, np.array(faces))


@pytest.mark.parametrize("a,b,length", [(1.0, 1.0, 1.0), (0.3, 0.8, 1.7), (2.0, 0.25, 0.1)])
def test_right_triangular_prism_closed_form(a, b, length):
    """Right triangle legs a (x), b (y), extruded by L along z, density rho, m = rho a b L / 2.

    COM = (a/3, b/3, L/2). About the COM, per unit mass, the triangle's area moments are
    <x'²> = a²/18, <y'²> = b²/18, <x'y'> = -a b/36, and the extrusion gives <z'²> = L²/12, so
        Ixx = m (b²/18 + L²/12),  Iyy = m (a²/18 + L²/12),  Izz = m (a² + b²)/18,
        Ixy = -m <x'y'> = +m a b / 36,  Ixz = Iyz = 0.
    """
    rho = 850.0
    m_expected = rho * a * b * length / 2
    expected = m_expected * np.array(
        [
            [b * b / 18 + length**2 / 12, a * b / 36, 0.0],
            [a * b / 36, a * a / 18 + length**2 / 12, 0.0],
            [0.0, 0.0, (a * a + b * b) / 18],
        ]
    )
    mesh = right_triangular_prism(a, b, length)
    for poly in (mesh, P.convex_hull(mesh.vertices)):
        assert_outward(poly)
        m, com, inertia = P.mass_properties(poly, rho)
        assert abs(m - m_expected) <= RTOL * m_expected
        assert rel_err(com, [a / 3, b / 3, length / 2]) < RTOL
        assert rel_err(inertia, expected) < RTOL


def ngon_area_moments(n, r):
    """(area, polar second moment about the centre) of a regular n-gon with circumradius r:
    A = n/2 r² sin(2π/n),  J = A r²/6 (2 + cos(2π/n)).

    Derivation: the n-gon is n isosceles triangles (0, p, q) with |p| = |q| = r, p.q = r² cos(2π/n);
    a triangle with a vertex at the origin has J = A/6 (|p|² + |q|² + p.q).
    """
    t = 2 * np.pi / n
    area = 0.5 * n * r * r * np.sin(t)
    return area, area * r * r / 6 * (2 + np.cos(t))


@pytest.mark.parametrize("n", [3, 4, 5, 6, 8, 13])
def test_ngon_formula_by_quadrature(n):
    """Check the closed form of the n-gon moments independently, in polar coordinates:
    the boundary is at distance R(φ) = r cos(π/n) / cos(φ) within each sector |φ| < π/n, so
    A = n ∫ R²/2 dφ and J = n ∫ R⁴/4 dφ."""
    r = 0.7
    apothem = r * np.cos(np.pi / n)
    area_q = n * integrate.quad(lambda p: (apothem / np.cos(p)) ** 2 / 2, -np.pi / n, np.pi / n, epsabs=0, epsrel=1e-13)[0]
    polar_q = n * integrate.quad(lambda p: (apothem / np.cos(p)) ** 4 / 4, -np.pi / n, np.pi / n, epsabs=0, epsrel=1e-13)[0]
    area, polar = ngon_area_moments(n, r)
    assert area == pytest.approx(area_q, rel=1e-12)
    assert polar == pytest.approx(polar_q, rel=1e-12)


def ngon_prism_expected(n, r, h, rho):
    """Mass and inertia (axial, transverse) of a regular n-gon prism about its COM.
    For n >= 3 the cross-section is isotropic in its plane, so each in-plane axis gets J/2."""
    area, polar = ngon_area_moments(n, r)
    m = rho * area * h
    axial = rho * h * polar
    transverse = rho * h * polar / 2 + m * h * h / 12
    return m, axial, transverse


def world_inertia(axis, axial, transverse):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    aa = np.outer(axis, axis)
    return transverse * (np.eye(3) - aa) + axial * aa


AXES = [
    ((0, 0, 0), (0, 0, 1.2)),
    ((0, 0, 0), (0, 0, -0.9)),
    ((0.1, 0.2, 0.3), (1.1, 0.2, 0.3)),
    ((0, 0, 0), (0, -2.0, 0)),
    ((0.5, -0.3, 1.0), (-0.2, 0.4, 0.1)),
    ((0, 0, 0), (1e-3, 1e-3, 1.0)),
]


@pytest.mark.parametrize("start,end", AXES)
@pytest.mark.parametrize("n", [3, 4, 6, 8, 11])
def test_prism_vertices_and_closed_form(start, end, n):
    r, rho = 0.15, 1000.0
    start, end = np.asarray(start, float), np.asarray(end, float)
    v = P.prism(start, end, r, sides=n)
    assert v.shape == (2 * n, 3)
    axis = (end - start) / np.linalg.norm(end - start)
    np.testing.assert_allclose(v[n:] - v[:n], np.tile(end - start, (n, 1)), atol=1e-14)
    ring = v[:n] - start
    np.testing.assert_allclose(ring @ axis, 0, atol=1e-14)  # ring plane is perpendicular
    np.testing.assert_allclose(np.linalg.norm(ring, axis=1), r, rtol=1e-14)  # on the circumcircle
    chords = np.linalg.norm(ring - np.roll(ring, -1, axis=0), axis=1)  # regular: equal sides
    np.testing.assert_allclose(chords, 2 * r * np.sin(np.pi / n), rtol=1e-13)

    h = np.linalg.norm(end - start)
    m_expected, axial, transverse = ngon_prism_expected(n, r, h, rho)
    poly = P.convex_hull(v)
    assert len(poly.vertices) == 2 * n
    m, com, inertia = P.mass_properties(poly, rho)
    assert abs(m - m_expected) <= RTOL * m_expected
    assert np.max(np.abs(com - (start + end) / 2)) <= 1e-14 * 10
    assert rel_err(inertia, world_inertia(axis, axial, transverse)) < 1e-12


def test_prism_converges_to_cylinder():
    r, h, rho = 0.2, 1.5, 1000.0
    m_cyl = rho * np.pi * r * r * h
    axial_cyl = m_cyl * r * r / 2
    transverse_cyl = m_cyl * (3 * r * r + h * h) / 12
    errors = []
    for n in (16, 64, 256):
        m, com, inertia = P.mass_properties(P.segment_hull([((0, 0, 0), (0, 0, h), r)], sides=n), rho)
        errors.append(
            max(abs(m - m_cyl) / m_cyl, abs(inertia[2, 2] - axial_cyl) / axial_cyl, abs(inertia[0, 0] - transverse_cyl) / transverse_cyl)
        )
    # Inscribed polygon: relative error ~ (2π/n)²/6, i.e. a factor 16 per 4x more sides.
    assert errors[0] > errors[1] > errors[2]
    assert errors[0] / errors[1] == pytest.approx(16, rel=0.05)
    assert errors[2] < 2 * (2 * np.pi / 256) ** 2 / 6
    assert errors[2] < 1e-3


def test_prism_rejects_bad_input():
    with pytest.raises(ValueError, match="sides"):
        P.prism((0, 0, 0), (0, 0, 1), 0.1, sides=2)
    with pytest.raises(ValueError, match="radius"):
        P.prism((0, 0, 0), (0, 0, 1), 0.0)
    with pytest.raises(ValueError, match="distinct"):
        P.prism((1, 2, 3), (1, 2, 3), 0.1)


def test_segment_hull_wraps_branching_bones():
    """A pelvis-like body: spine up and two hips; the hull contains every prism and is convex."""
    segs = [
        ((0, 0, 0), (0, 0, 0.25), 0.08),
        ((0, 0, 0), (0.12, -0.05, -0.08), 0.05),
        ((0, 0, 0), (-0.12, -0.05, -0.08), 0.05),
    ]
    poly = P.segment_hull(segs, sides=8)
    cloud = np.concatenate([P.prism(s, e, r, 8) for s, e, r in segs])
    # Hull vertices are a subset of the prism vertices.
    d = np.linalg.norm(poly.vertices[:, None] - cloud[None], axis=-1)
    assert np.all(d.min(1) == 0)
    # Convex and outward: every point lies on the inner side of every face plane.
    tri = poly.vertices[poly.faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    signed = np.einsum("fj,fpj->fp", normal, cloud[None] - tri[:, None, 0])
    assert signed.max() < 1e-12
    m, com, inertia = P.mass_properties(poly)
    assert_valid_inertia(inertia)
    # Larger than the largest single prism, and symmetric in x (mirror hips).
    m_spine = ngon_prism_expected(8, 0.08, 0.25, 1000.0)[0]
    assert m > m_spine
    assert abs(com[0]) < 1e-14
    assert abs(inertia[0, 1]) < 1e-12 * np.trace(inertia) and abs(inertia[0, 2]) < 1e-12 * np.trace(inertia)
    with pytest.raises(ValueError):
        P.segment_hull([])


# ----------------------------------------------------------------------------- non-convex meshes


def extrude(polygon, z0, z1):
    """Closed mesh of a counter-clockwise (seen from +z) polygon extruded over [z0, z1].
    The caps are fanned from vertex 0, which must see the whole polygon (star-shaped)."""
    poly2 = np.asarray(polygon, float)
    k = len(poly2)
    bottom = np.column_stack([poly2, np.full(k, z0)])
    top = np.column_stack([poly2, np.full(k, z1)])
    faces = []
    for i in range(1, k - 1):
        faces.append([0, i + 1, i])  # bottom cap, normal -z
        faces.append([k, k + i, k + i + 1])  # top cap, normal +z
    for i in range(k):
        j = (i + 1) % k
        faces.append([i, j, k + j])
        faces.append([i, k + j, k + i])
    return P.Polyhedron(np.concatenate([bottom, top]), np.array(faces))


def composite(parts):
    """Combine (mass, com, inertia about own com) of disjoint parts; a negative mass subtracts."""
    m = sum(p[0] for p in parts)
    com = sum(p[0] * np.asarray(p[1]) for p in parts) / m
    inertia = sum(shift_inertia(p[2], p[0], np.asarray(p[1]) - com) for p in parts)
    return m, com, inertia


def box_part(lo, hi, rho):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    m = rho * np.prod(size)
    return m, (lo + hi) / 2, box_inertia(m, *size)


def test_l_shaped_prism_is_exact():
    """Non-convex L: the unit squares [0,2]x[0,1] and [0,1]x[1,2], extruded over z in [0, 0.5]."""
    rho = 1000.0
    mesh = extrude([(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)], 0.0, 0.5)
    m, com, inertia = P.mass_properties(mesh, rho)
    m_e, com_e, inertia_e = composite([box_part((0, 0, 0), (2, 1, 0.5), rho), box_part((0, 1, 0), (1, 2, 0.5), rho)])
    assert abs(m - m_e) <= RTOL * m_e
    assert rel_err(com, com_e) < RTOL
    assert rel_err(inertia, inertia_e) < RTOL
    assert abs(inertia[0, 1]) > 1.0  # the L has a real product of inertia (test is not trivial)
    # ... and differs from its convex hull, which fills in the notch.
    m_hull = P.mass_properties(P.convex_hull(mesh.vertices), rho)[0]
    assert m_hull == pytest.approx(m * 3.5 / 3.0, rel=RTOL)


def test_box_with_cavity_is_exact():
    """Outer box plus an inner box with reversed faces (normals into the cavity) = hollow solid."""
    rho = 500.0
    outer = P.box([1.0, 0.8, 0.6])
    inner_lo, inner_hi = np.array([-0.2, 0.1, -0.3]), np.array([0.7, 0.5, 0.4])
    inner = P.box((inner_hi - inner_lo) / 2)
    inner_v = inner.vertices + (inner_lo + inner_hi) / 2
    mesh = P.Polyhedron(
        np.concatenate([outer.vertices, inner_v]), np.concatenate([outer.faces, inner.faces[:, ::-1] + 8])
    )
    m, com, inertia = P.mass_properties(mesh, rho)
    o = box_part((-1.0, -0.8, -0.6), (1.0, 0.8, 0.6), rho)
    i = box_part(inner_lo, inner_hi, rho)
    m_e, com_e, inertia_e = composite([o, (-i[0], i[1], -i[2])])
    assert abs(m - m_e) <= RTOL * m_e
    assert rel_err(com, com_e) < 1e-11
    assert rel_err(inertia, inertia_e) < RTOL
    assert_valid_inertia(inertia)


def test_split_box_is_additive():
    """A box cut into two boxes: the parts' mass properties combine to the whole's."""
    rho = 1000.0
    whole = P.mass_properties(P.box([0.5, 0.3, 0.2]), rho)
    left = transformed(P.box([0.2, 0.3, 0.2]), np.eye(3), [-0.3, 0, 0])
    right = transformed(P.box([0.3, 0.3, 0.2]), np.eye(3), [0.2, 0, 0])
    m, com, inertia = composite([P.mass_properties(left, rho), P.mass_properties(right, rho)])
    assert abs(m - whole[0]) <= RTOL * whole[0]
    assert np.max(np.abs(com - whole[1])) < 1e-15
    assert rel_err(inertia, whole[2]) < RTOL


# ----------------------------------------------------------------------------- invariance (hypothesis)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(4, 40),
    log_scale=st.floats(-2.0, 1.0),
    far=st.floats(0.0, 50.0),
)
def test_hull_mass_properties_invariance(seed, n, log_scale, far):
    rng = np.random.default_rng(seed)
    scale = 10.0**log_scale
    points = rng.normal(size=(n, 3)) * rng.uniform(0.2, 1.0, 3) * scale
    try:
        poly = P.convex_hull(points)
    except ValueError:  # a (nearly) flat sample of few points; genuinely degenerate
        return
    assert_outward(poly)
    m, com, inertia = P.mass_properties(poly, 1000.0)
    assert m > 0
    assert_valid_inertia(inertia)
    # The hull's COM lies inside the hull's bounding box.
    assert np.all(com >= poly.vertices.min(0) - 1e-12 * scale) and np.all(com <= poly.vertices.max(0) + 1e-12 * scale)

    rot = Rotation.random(random_state=rng).as_matrix()
    shift = rng.normal(size=3) * far * scale
    m2, com2, inertia2 = P.mass_properties(P.convex_hull(points @ rot.T + shift), 1000.0)
    tol = 1e-10 * (1 + far)
    assert abs(m2 - m) <= tol * m
    assert np.max(np.abs(com2 - (rot @ com + shift))) <= tol * scale
    assert rel_err(inertia2, rot @ inertia @ rot.T) < tol
    assert_valid_inertia(inertia2)

    # Density scales mass and inertia linearly and leaves the COM alone.
    m3, com3, inertia3 = P.mass_properties(poly, 2.5)
    assert m3 == pytest.approx(m * 2.5e-3, rel=1e-13)
    np.testing.assert_array_equal(com3, com)
    assert rel_err(inertia3, inertia * 2.5e-3) < 1e-13


# ----------------------------------------------------------------------------- invalid meshes


def test_inward_mesh_is_rejected():
    cube = P.box([0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="non-positive volume"):
        P.mass_properties(P.Polyhedron(cube.vertices, cube.faces[:, ::-1]))
    hull = P.segment_hull([((0, 0, 0), (0.3, 0.1, 0.2), 0.05)])
    with pytest.raises(ValueError, match="oriented outward"):
        P.mass_properties(P.Polyhedron(hull.vertices, hull.faces[:, [0, 2, 1]]))


def test_open_or_partly_flipped_mesh_is_rejected():
    cube = P.box([0.5, 0.5, 0.5])
    one_flipped = cube.faces.copy()
    one_flipped[3] = one_flipped[3, ::-1]
    with pytest.raises(ValueError, match="not closed"):
        P.mass_properties(P.Polyhedron(cube.vertices, one_flipped))
    with pytest.raises(ValueError, match="not closed"):
        P.mass_properties(P.Polyhedron(cube.vertices, cube.faces[:-1]))
    # Two opposite faces missing: the vector area still sums to zero, but the flux check catches it.
    with pytest.raises(ValueError, match="not closed"):
        P.mass_properties(P.Polyhedron(cube.vertices, cube.faces[4:]))
    with pytest.raises(ValueError, match="density"):
        P.mass_properties(cube, density=0.0)


def test_polyhedron_validates_and_freezes():
    cube = P.box(0.5)
    assert cube.vertices.dtype == np.float64 and cube.faces.dtype == np.int64
    assert cube.vertices.shape == (8, 3) and cube.faces.shape == (12, 3)
    with pytest.raises(ValueError):
        cube.vertices[0, 0] = 3.0
    with pytest.raises(ValueError, match="face indices"):
        P.Polyhedron(cube.vertices, cube.faces + 1)
    with pytest.raises(ValueError, match="shape"):
        P.Polyhedron(cube.vertices[:, :2], cube.faces)
    hull = P.convex_hull(cube.vertices)
    assert hull.faces.dtype == np.int64


@pytest.mark.parametrize(
    "points",
    [
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float),  # too few
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.3, 0.2, 0]], float),  # coplanar
        np.outer(np.linspace(0, 1, 6), [1.0, 2.0, 3.0]),  # collinear
        np.ones((5, 3)),  # all the same point
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-15]], float),  # numerically flat
    ],
)
def test_degenerate_hull_is_rejected(points):
    with pytest.raises(ValueError, match="degenerate"):
        P.convex_hull(points)


def test_nonfinite_or_misshaped_points_are_rejected():
    with pytest.raises(ValueError, match="finite"):
        P.convex_hull(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan]]))
    with pytest.raises(ValueError, match="shape"):
        P.convex_hull(np.zeros((5, 2)))
