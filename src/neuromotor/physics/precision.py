"""The floating-point precision a rollout runs in, and the cast that puts a pytree into it.

JAX runs with x64 enabled throughout; float32 mode casts the floating leaves of the model, the
mocap reference, the initial state and the parameters (gains, pulses) to float32 at the entry of
a rollout (:func:`neuromotor.physics.dynamics.simulate`), and every op of the step then stays in
the dtype of its inputs (``tests/physics/test_float32.py`` checks the step's program holds no
float64 value). Inverse dynamics and the reference are prepared in float64 and cast at the end.
What float32 costs in accuracy is measured in docs/float32.md.
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax
import jax.numpy as jnp


class Precision(str, enum.Enum):
    """The dtype of a rollout's floating arrays (``StepOptions.dtype``; the strings are accepted too)."""

    FLOAT64 = "float64"  # the reference path: KKT residual ~1e-13, constraint drift ~1e-14
    FLOAT32 = "float32"  # for sweeps and accelerators: see docs/float32.md for what it loses

    def __str__(self) -> str:
        return self.value

    @property
    def dtype(self):
        return jnp.float64 if self is Precision.FLOAT64 else jnp.float32


def cast(tree, precision: Precision | str):
    """``tree`` with every floating array leaf in ``precision``'s dtype (other leaves unchanged;
    a leaf already in that dtype is returned as is, so the cast is free on the float64 path)."""
    dtype = Precision(precision).dtype

    def leaf(x):
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) and x.dtype != dtype:
            return x.astype(dtype)
        return x

    return jax.tree_util.tree_map(leaf, tree)
