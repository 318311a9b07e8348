"""Recovery metrics of a perturbed rollout against its unperturbed twin.

The deviation signal (``metric = "geodesic"``, the default) is the RMS over the simulated joints
of each joint's geodesic angle: with R_a, R_b a joint's local rotations (R_parent^T R_child) in
the two runs, ``d(t) = sqrt(mean_j angle(R_a,j^T R_b,j)^2)`` in degrees (:func:`joint_deviation`).
It does not depend on how the clip writes its angles (Euler order, branch, gimbal lock), and it
never exceeds the largest single joint's rotation change. ``metric = "euler"`` keeps the older
per-DOF form ``d(t) = sqrt(mean_i wrap(theta_i - theta_unperturbed_i)^2)`` over the Euler angles
(:func:`deviation`), where ``wrap`` gives the shortest signed angle; for small rotations it reads
about 1/sqrt(3) of the geodesic RMS (three DOFs share one joint's rotation), and near gimbal lock
two of a joint's angles can swing by opposite large amounts while the joint barely turns. From
d(t):

* peak deviation (deg) and its time (s);
* recovery time (s): from the perturbation's start until d(t) falls below
  ``max(recovery_fraction * peak, recovery_floor_deg)`` and stays below to the end (NaN if it
  never does);
* final error (deg): d at the last sample;
* overshoot (deg): the largest deviation after the first time d drops below the threshold.

Each has a smooth surrogate for gradient-based fitting: a log-sum-exp peak, a softmax-weighted
peak time, and a sigmoid-integrated recovery time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.config.specs import (
    DEVIATION_METRICS,
    RECOVERY_FLOOR_DEG,
    RECOVERY_FRACTION,
)
from neuromotor.rotations import quat_conj, quat_log, quat_mul, quat_rotate


def wrap_angle(a):
    """The angle equal to ``a`` modulo 2 pi in [-pi, pi] (the shortest signed difference when
    ``a`` is a difference of angles). ``atan2(sin a, cos a)``: smooth, with derivative 1
    everywhere, so it can sit inside ``jacfwd``/``grad`` (fitting)."""
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def wrap_angle_np(a) -> np.ndarray:
    """:func:`wrap_angle` in NumPy (no device round trip)."""
    a = np.asarray(a, dtype=np.float64)
    return np.arctan2(np.sin(a), np.cos(a))


def deviation(theta, theta_ref, dofs=None) -> Float[Array, " T"]:
    """RMS over DOFs of the wrapped (shortest) angle difference, degrees, per time sample."""
    diff = wrap_angle(theta - theta_ref)
    if dofs is not None:
        diff = diff[:, jnp.asarray(dofs)]
    return jnp.rad2deg(jnp.sqrt(jnp.mean(diff**2, axis=-1)))


def rms_error_deg(theta, theta_ref) -> float:
    """RMS of the wrapped angle differences over all samples and DOFs, degrees (Euler form)."""
    diff = wrap_angle_np(np.asarray(theta) - np.asarray(theta_ref))
    return float(np.rad2deg(np.sqrt(np.mean(diff**2))))


# ---------------------------------------------------------------- geodesic joint errors


def _topology(model_or_topology):
    return getattr(model_or_topology, "topology", model_or_topology)


def safe_sqrt(u):
    """sqrt(u) with derivative 0 (not NaN) where u = 0: identical runs give exactly 0 before a
    hit, and d sqrt(u) = du / 2 sqrt(u) would put 0/0 in a fit's Jacobian (double ``where``)."""
    pos = u > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, u, 1.0)), 0.0)


def joint_quats(model_or_topology, quat: Float[Array, "... B 4"]) -> Float[Array, "... C 4"]:
    """Each joint's local rotation q_parent^* q_child from body quaternions (w, x, y, z); joint
    rows are bodies 1..B-1 (the root has no joint), in ``topology.child`` order."""
    topo = _topology(model_or_topology)
    return quat_mul(quat_conj(quat[..., topo.parent, :]), quat[..., topo.child, :])


def joint_rates(
    model_or_topology, quat: Float[Array, "... B 4"], omega: Float[Array, "... B 3"]
) -> Float[Array, "... C 3"]:
    """Each joint's relative angular velocity R_child^T (w_child - w_parent) (rad/s, in the
    child's frame, like :func:`rotation_vector`) from body quaternions and world angular velocities."""
    topo = _topology(model_or_topology)
    q_c = quat[..., topo.child, :]
    return quat_rotate(quat_conj(q_c), omega[..., topo.child, :] - omega[..., topo.parent, :])


def dof_selection(model, dofs) -> tuple[np.ndarray, np.ndarray]:
    """Joint rows (of :func:`joint_quats`) of the simulated DOFs ``dofs`` and an (R, 3) mask of
    their axes: the coordinate axis of each DOF's name (``Chest.Xrotation``: x) in its joint's
    child frame. A whole joint (all three DOFs) selects its whole rotation."""
    topo = _topology(model)
    bodies = sorted({int(topo.dof_body[int(i)]) for i in dofs})
    mask = np.zeros((len(bodies), 3))
    for i in dofs:
        axis = str(model.dof_names[int(i)]).rsplit(".", 1)[-1][:1].upper()
        mask[bodies.index(int(topo.dof_body[int(i)])), "XYZ".index(axis)] = 1.0
    return joint_rows(topo, bodies), mask


def selected_deviation_deg(local_a, local_b, rows, mask) -> Float[Array, ...]:
    """d(t) (deg) over a selection of joints and axes (:func:`dof_selection`):
    ``sqrt(sum_j sum_axes mask (phi_j . e)^2 / R)``, phi_j the rotation vector between the two
    runs' local rotations of joint j. Whole joints give the geodesic RMS exactly; one axis per
    joint gives the RMS over joints of the signed turn about that body axis (a flexion, say),
    which, unlike an Euler angle, does not depend on the Euler order."""
    a, b = local_a[..., jnp.asarray(rows), :], local_b[..., jnp.asarray(rows), :]
    if np.all(mask):
        return rms_joint_angle_deg(a, b)
    phi = rotation_vector(a, b)
    return jnp.rad2deg(safe_sqrt(jnp.sum(jnp.asarray(mask) * phi**2, axis=(-1, -2)) / len(rows)))


def joint_rows(model_or_topology, joints=None) -> np.ndarray:
    """Rows (of :func:`joint_quats`) of the body indices ``joints`` (None: every joint)."""
    topo = _topology(model_or_topology)
    if joints is None:
        return np.arange(len(topo.child))
    joints = np.asarray(joints, dtype=np.int64)
    rows = np.minimum(np.searchsorted(topo.child, joints), len(topo.child) - 1)
    if not np.array_equal(np.asarray(topo.child)[rows], joints):  # the root (0) has no joint
        raise ValueError(f"joints must be non-root body indices, got {joints.tolist()}")
    return np.asarray(rows, dtype=np.int64)


def dof_joints(model_or_topology, dofs) -> tuple[int, ...]:
    """The bodies (joints) that the simulated DOF indices ``dofs`` turn, each once, sorted."""
    topo = _topology(model_or_topology)
    return tuple(sorted({int(topo.dof_body[int(i)]) for i in dofs}))


def geodesic_angle(q_a: Float[Array, "... 4"], q_b: Float[Array, "... 4"]) -> Float[Array, ...]:
    """Angle (rad, in [0, pi]) of the rotation q_a^* q_b: ``2 atan2(|v|, |w|)`` of the relative
    quaternion (accurate at small and large angles, the same for q and -q). Its derivative at
    zero angle is taken as 0 (safe norm), so fits that start from identical runs stay finite."""
    rel = quat_mul(quat_conj(q_a), q_b)
    v = rel[..., 1:]
    return 2.0 * jnp.arctan2(safe_sqrt(jnp.sum(v * v, axis=-1)), jnp.abs(rel[..., 0]))


def rotation_vector(q_d: Float[Array, "... 4"], q: Float[Array, "... 4"]) -> Float[Array, "... 3"]:
    """Signed rotation vector (rad) log(R_d^T R) of q_d^* q, in q_d's frame: the shortest turn
    from q_d to q; its norm is :func:`geodesic_angle`. For residuals that need a sign."""
    return quat_log(quat_mul(quat_conj(q_d), q))


def rms_joint_angle_deg(local_a, local_b, rows=None) -> Float[Array, ...]:
    """RMS over joints (the last axis but one; ``rows`` picks some) of the geodesic angle
    between two sets of local joint quaternions, degrees."""
    ang = geodesic_angle(local_a, local_b)
    if rows is not None:
        ang = ang[..., jnp.asarray(rows)]
    return jnp.rad2deg(safe_sqrt(jnp.mean(ang**2, axis=-1)))


def joint_deviation(
    model_or_topology, quat_a: Float[Array, "T B 4"], quat_b: Float[Array, "T B 4"], joints=None
) -> Float[Array, " T"]:
    """The geodesic deviation d(t) (deg) of two runs' body quaternions (``Rollout.states.quat``):
    per sample, the RMS over the simulated joints (``joints``: body indices; None: all) of the
    angle of R_a^T R_b of each joint's local rotations. Jittable, vmappable, differentiable."""
    rows = None if joints is None else joint_rows(model_or_topology, joints)
    return rms_joint_angle_deg(joint_quats(model_or_topology, quat_a), joint_quats(model_or_topology, quat_b), rows)


def joint_angle_changes_deg(model_or_topology, quat_a, quat_b) -> Float[Array, "T C"]:
    """Per sample and joint, the geodesic angle (deg) between the two runs' local rotations."""
    return jnp.rad2deg(geodesic_angle(joint_quats(model_or_topology, quat_a), joint_quats(model_or_topology, quat_b)))


def rms_joint_error_deg(model_or_topology, quat, ref_quat: Float[Array, "T C 4"]) -> float:
    """RMS over all samples and joints of the geodesic angle (deg) between a run's local joint
    rotations and desired ones (``Reference.rel_quat``: the mocap's on the grid)."""
    ang = geodesic_angle(joint_quats(model_or_topology, quat), ref_quat)
    return float(np.rad2deg(np.sqrt(np.mean(np.asarray(ang) ** 2))))


def run_deviation(metric: str, model_or_topology, run_a, run_b, joints=None) -> Float[Array, " T"]:
    """d(t) of two rollouts by the named metric: ``"geodesic"`` (:func:`joint_deviation` on
    their ``states.quat``) or ``"euler"`` (:func:`deviation` on their ``theta``; ``joints``
    then picks those joints' DOFs)."""
    if metric == "geodesic":
        return joint_deviation(model_or_topology, run_a.states.quat, run_b.states.quat, joints)
    if metric == "euler":
        dofs = None
        if joints is not None:
            body = np.asarray(_topology(model_or_topology).dof_body)
            dofs = np.nonzero(np.isin(body, np.asarray(joints)))[0]
        return deviation(run_a.theta, run_b.theta, dofs)
    raise ValueError(f"metric must be one of {DEVIATION_METRICS}, got {metric!r}")


def recovery_metrics(
    time, dev, start: float, fraction: float = RECOVERY_FRACTION, floor_deg: float = RECOVERY_FLOOR_DEG
) -> dict[str, float]:
    """Exact (non-smooth) metrics of a deviation signal, as plain floats."""
    time, dev = np.asarray(time), np.asarray(dev)
    ipk = int(np.argmax(dev))
    peak = float(dev[ipk])
    thr = max(fraction * peak, floor_deg)
    after = time >= start
    above = (dev > thr) & after
    if peak <= floor_deg:
        rec, first_below = 0.0, ipk
    elif above[-1]:
        rec, first_below = float("nan"), len(dev)
    else:
        last_above = int(np.nonzero(above)[0][-1]) if above.any() else ipk
        rec = float(time[last_above + 1] - start)
        below = np.nonzero((dev <= thr) & (time > time[ipk]))[0]
        first_below = int(below[0]) if below.size else len(dev)
    overshoot = float(dev[first_below:].max()) if first_below < len(dev) else 0.0
    return {
        "peak_deviation_deg": peak,
        "time_of_peak_s": float(time[ipk]),
        "recovery_time_s": rec,
        "final_error_deg": float(dev[-1]),
        "overshoot_deg": overshoot,
        "recovery_threshold_deg": thr,
    }


def soft_peak(dev, beta: float = 5.0):
    """Smooth max: (1/beta) log sum exp(beta d) - (1/beta) log T (exact as beta -> inf)."""
    return (jax.nn.logsumexp(beta * dev) - jnp.log(dev.shape[0])) / beta


def soft_time_of_peak(time, dev, beta: float = 5.0):
    w = jax.nn.softmax(beta * dev)
    return jnp.sum(w * time)


def soft_overshoot(time, dev, t_return, beta: float = 5.0):
    """Smooth peak of the deviation after the (soft) return time ``t_return``."""
    gate = jax.nn.sigmoid((time - t_return) / (time[1] - time[0]))
    return soft_peak(dev * gate, beta)
