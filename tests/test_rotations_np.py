"""neuromotor.rotations_np, the NumPy twin of neuromotor.rotations: the same numbers (to 1e-12)
with the same arguments in the same order, gimbal lock included, and the conventions of scipy."""

import inspect
import itertools

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neuromotor import rotations, rotations_np

TAIT_BRYAN = ["".join(p) for p in itertools.permutations("XYZ")]
PROPER = [a + b + a for a in "XYZ" for b in "XYZ" if b != a]  # not BVH orders; matrices only


def _angles(seed: int, n: int = 400) -> np.ndarray:
    """Random angles, the middle one at, and within 1e-9 .. 1e-5 of, +-pi/2 in a quarter of rows."""
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-np.pi, np.pi, size=(n, 3))
    q = n // 8
    angles[:q, 1] = np.pi / 2
    angles[q:2 * q, 1] = -np.pi / 2
    angles[2 * q:3 * q, 1] = np.pi / 2 - 10.0 ** rng.uniform(-9, -5, q)
    return angles


def test_same_names_and_argument_order():
    for name in ("axis_rotation", "euler_to_matrix", "matrix_to_euler", "wrap_angle"):
        twin, jax_fn = getattr(rotations_np, name), getattr(rotations, name)
        assert list(inspect.signature(twin).parameters) == list(inspect.signature(jax_fn).parameters), name


@pytest.mark.parametrize("order", TAIT_BRYAN + PROPER)
def test_euler_to_matrix_equals_jax_and_scipy(order):
    angles = _angles(1)
    r = rotations_np.euler_to_matrix(angles, order)
    np.testing.assert_allclose(r, np.asarray(rotations.euler_to_matrix(jnp.asarray(angles), order)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(r, Rotation.from_euler(order, angles).as_matrix(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("order", TAIT_BRYAN)
def test_matrix_to_euler_equals_jax(order):
    angles = _angles(2)
    r = rotations_np.euler_to_matrix(angles, order)
    jr = jnp.asarray(r)
    back = rotations_np.matrix_to_euler(r, order)
    np.testing.assert_allclose(back, np.asarray(rotations.matrix_to_euler(jr, order)), rtol=0, atol=1e-12)
    clear = np.abs(np.cos(angles[:, 1])) > 1e-4  # off lock, the angles themselves round-trip
    np.testing.assert_allclose(rotations_np.euler_to_matrix(back[clear], order), r[clear], rtol=0, atol=1e-12)
    assert np.all(np.abs(back[:, 1]) <= np.pi / 2 + 1e-12)
    # With a reference: the branch nearest it, unwrapped to it, t1 from it at lock.
    rng = np.random.default_rng(3)
    reference = angles + rng.normal(scale=0.3, size=angles.shape) + 2 * np.pi * rng.integers(-2, 3, angles.shape)
    near = rotations_np.matrix_to_euler(r, order, reference)
    np.testing.assert_allclose(near, np.asarray(rotations.matrix_to_euler(jr, order, jnp.asarray(reference))),
                               rtol=0, atol=1e-12)
    # (within 1e-7 of lock t1 is the reference's: the matrix is then off by up to |cos t2|)
    np.testing.assert_allclose(rotations_np.euler_to_matrix(near, order), r, rtol=0, atol=2e-7)
    assert np.all(np.abs(near - reference) <= np.pi + 1e-12)


@pytest.mark.parametrize("order", PROPER)
def test_proper_euler_orders_are_refused_by_both(order):
    r = np.eye(3)
    with pytest.raises(ValueError):
        rotations.matrix_to_euler(jnp.asarray(r), order)
    with pytest.raises(ValueError):
        rotations_np.matrix_to_euler(r, order)


def test_wrap_and_rotation_angle():
    x = np.linspace(-20, 20, 1001)
    np.testing.assert_allclose(rotations_np.wrap_angle(x), np.asarray(rotations.wrap_angle(jnp.asarray(x))),
                               rtol=0, atol=1e-12)
    angles = _angles(4)
    r = rotations_np.euler_to_matrix(angles, "ZXY")
    want = np.linalg.norm(Rotation.from_matrix(r).as_rotvec(), axis=1)
    np.testing.assert_allclose(rotations_np.rotation_angle(r), want, rtol=0, atol=1e-7)


def test_quaternion_twins_equal_jax():
    """quat_mul, quat_conj, quat_exp and quat_log (a tilted ground's orientation on the host)
    give the JAX functions' numbers, small and near-pi angles included."""
    for name in ("quat_mul", "quat_conj", "quat_exp", "quat_log"):
        twin, jax_fn = getattr(rotations_np, name), getattr(rotations, name)
        assert list(inspect.signature(twin).parameters) == list(inspect.signature(jax_fn).parameters), name
    rng = np.random.default_rng(4)
    w = rng.normal(size=(300, 3)) * np.concatenate([np.full(100, 1e-7), np.full(100, 1.0), np.full(100, 3.1)])[:, None]
    q = rotations_np.quat_exp(w)
    np.testing.assert_allclose(q, np.asarray(rotations.quat_exp(jnp.asarray(w))), rtol=0, atol=1e-12)
    np.testing.assert_allclose(rotations_np.quat_log(q), np.asarray(rotations.quat_log(jnp.asarray(q))), rtol=0,
                               atol=1e-12)
    short = np.linalg.norm(w, axis=-1) < np.pi - 1e-3  # beyond pi the log is the shorter turn
    np.testing.assert_allclose(rotations_np.quat_log(q)[short], w[short], rtol=0, atol=1e-9)
    p = q[::-1]
    np.testing.assert_allclose(rotations_np.quat_mul(p, rotations_np.quat_conj(q)),
                               np.asarray(rotations.quat_mul(jnp.asarray(p), rotations.quat_conj(jnp.asarray(q)))),
                               rtol=0, atol=1e-12)
