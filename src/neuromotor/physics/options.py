"""The choices of how a simulation reads the capture (``StepOptions.feedforward``, ``StepOptions.joint_law``).

A light module (no JAX): the config parser imports it without loading the physics.
"""

from __future__ import annotations

import enum


class Feedforward(str, enum.Enum):
    """Where the feedforward multipliers come from (``StepOptions.feedforward``)."""

    DISCRETE = "discrete"  # the exact inverse of this step (physics/discrete.py): the replay is the capture
    CONTINUOUS = "continuous"  # Eq. 3 on the spline (the paper's): O(h) drift for the feedback to absorb

    def __str__(self) -> str:
        return self.value


class JointLaw(str, enum.Enum):
    """How a ball joint's feedforward and feedback are resolved (``StepOptions.joint_law``)."""

    ROTATION = "rotation"  # one 3-vector law in the parent's frame: the same for every Euler order
    EULER = "euler"  # the paper's per Euler DOF (damped at gimbal lock)

    def __str__(self) -> str:
        return self.value
