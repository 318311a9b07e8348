"""Forward dynamics (Eq. 2): a linearly implicit step, post-stabilization, and the rollout.

One step from t to t + h (Anitescu & Potra's linearly implicit scheme, Section 4.1):

    [ M - h D - h^2 K   -J^T ] [ v+  ]   [ M v + h (k - D v) ]
    [       J             0  ] [ lam ] = [       b(t+h)      ]          (2)

with k = f_ext + H^T (tau + feedback) + perturbations, K = dk/dx over the position tangent space
and D = dk/dv, both in closed form (:mod:`neuromotor.physics.stiffness`; ``jax.jacfwd`` of k
is the check, ``StepOptions.jacobians``). b carries the
driven root's (and driven joints') velocity. Positions then move with v+ (quaternions by the
exponential map) and are projected back onto the constraint manifold (Cline & Pai 2003) by
``StepOptions.stabilization_steps`` Newton steps (:func:`neuromotor.physics.constraints.post_stabilize`).
Two by default: one leaves up to 3.6e-8 m of violation on the default hit, two leave 1e-14 m
and give the same motion as three to 1e-13.

The step, in the style of MuJoCo MJX's ``forward``, is ``step(sim, params, data) -> data`` over
three pytrees:

* :class:`SimModel` -- what stays fixed over a rollout: the skeleton ``Model``, the mocap
  :class:`Reference` on the time grid and the static :class:`StepOptions`;
* :class:`Params` -- what a user fits or sweeps: the controller's :class:`Gains` and the
  perturbation :class:`ForcePulses`;
* :class:`Data` -- what a step advances: the grid index k, the :class:`State` and the
  :class:`StepInfo` diagnostics of the step that produced it;

and reads as a sequence of named stages: controller inputs, stiff forces with K and D (muscle
torques of Eq. 4 and Section 5.2, gyroscopic term), applied forces, the right-hand side of
Eq. 2, KKT assembly and solve (by the chosen :class:`Solver`), integration, post-stabilization.
Every solver gives the same step (tests check agreement to round-off) and records the relative
residual of the whole of Eq. 2 and the constraint violation left after post-stabilization.

The rollout, ``simulate(sim, params) -> Rollout``, is one ``lax.scan`` of :func:`step`: the one
way to run (the studies, fits, sweeps and experiments call it; the contact rollout scans its
own step the same way; :func:`rollout` is a thin convenience for users over the separate
pieces). Divergence is recorded in the carry (first bad step and body) and raised on the host
by :func:`check_rollout`. Joint angles and rates are
computed after the scan for all states at once.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from neuromotor import compiler
from neuromotor.errors import UserError
from neuromotor.model.kinematics import Trajectory, body_kinematics, joint_angles_from_q
from neuromotor.model.skeleton import Model
from neuromotor.physics import solvers
from neuromotor.physics.balance import (
    Balance,
    Posture,
    assist_force,
    balance_torques,
    empty_posture,
    swing_reference,
)
from neuromotor.physics.constraints import PoseTargets, constraint_count, constraint_velocity, post_stabilize
from neuromotor.physics.control import (
    ControllerInputs,
    Gains,
    body_torques,
    controller_inputs,
    damped_pinv,
    joint_errors,
    joint_local_axes,
    joint_torque_magnitude,
    reflex_torque,
)
from neuromotor.physics.discrete import discrete_inverse_dynamics, landing_velocities
from neuromotor.physics.inverse import inverse_dynamics, sim_columns
from neuromotor.physics.options import Feedforward, JointLaw
from neuromotor.physics.perturbation import ForcePulses, no_pulses, pulse_wrenches
from neuromotor.physics.precision import Precision, cast
from neuromotor.physics.reflex import History, empty_history, push
from neuromotor.physics.solvers import Solver
from neuromotor.physics.stiffness import (
    DenseStiffness,
    Jacobians,
    StiffBlocks,
    explicit_forces,
    stiff_blocks,
    stiff_jacobians,
)
from neuromotor.physics.system import (
    State,
    dof_axes,
    dofs_to_per_joint,
    gravity_forces,
    joint_angles_and_rates,
    joint_rates,
    mass_times,
    per_joint_to_dofs,
    retract,
    world_inertia,
)
from neuromotor.rotations import matrix_to_quat, mm


class SimulationDiverged(UserError, RuntimeError):
    """Raised when a rollout blows up; names the step, the time and the body."""

    def __init__(self, step: int, time: float, body: str, reason: str = "non-finite or runaway state"):
        self.step, self.time, self.body = step, time, body
        super().__init__(f"simulation diverged at step {step} (t = {time:.4f} s) in body {body!r}: {reason}")


class StepOptions(eqx.Module):
    """Static settings of a rollout."""

    h: float = eqx.field(static=True, default=1.0 / 120.0)
    n_steps: int = eqx.field(static=True, default=120)
    driven: tuple[int, ...] = eqx.field(static=True, default=())  # bodies driven along the mocap
    implicit: bool = eqx.field(static=True, default=True)  # False: K = D = 0 (explicit forces)
    # Newton steps of post-stabilization: 2 reach round-off (see the module docstring)
    stabilization_steps: int = eqx.field(static=True, default=2)
    max_speed: float = eqx.field(static=True, default=200.0)  # rad/s or m/s: beyond it, diverged
    free_root: bool = eqx.field(static=True, default=False)  # drop the 6 driven-root rows
    # The solver of Eq. 2 (a Solver or its string): null-space (default, fastest), branch (its
    # batched twin, for vmapped sweeps), tree, dense.
    solver: Solver = eqx.field(static=True, default=Solver.NULLSPACE, converter=Solver)
    # The dtype of the rollout's arrays (a Precision or its string): float64, or float32 (docs/float32.md).
    dtype: Precision = eqx.field(static=True, default=Precision.FLOAT64, converter=Precision)
    # How the tree solvers get K and D: closed form (default) or jax.jacfwd (the check); equal to round-off.
    jacobians: Jacobians = eqx.field(static=True, default=Jacobians.CLOSED_FORM, converter=Jacobians)
    # The feedforward: the discrete inverse of this step (default) or the paper's Eq. 3.
    feedforward: Feedforward = eqx.field(static=True, default=Feedforward.DISCRETE, converter=Feedforward)
    # Ball joints' controller: one rotation law (default, frame-invariant) or the paper's per Euler DOF.
    joint_law: JointLaw = eqx.field(static=True, default=JointLaw.ROTATION, converter=JointLaw)


class Reference(eqx.Module):
    """Mocap targets on the simulation grid t_k = t0 + k h, k = 0..S."""

    time: Float[Array, " S1"]
    tau: Float[Array, "S1 n"]  # feedforward multipliers (discrete inverse dynamics, or Eq. 3)
    activation: Float[Array, "S1 n"]  # |T_j| of each DOF's joint (see control)
    theta: Float[Array, "S1 n"]  # desired Euler angles theta_d
    theta_dot: Float[Array, "S1 n"]
    root_origin: Float[Array, "S1 3"]
    root_rot: Float[Array, "S1 3 3"]
    root_vel: Float[Array, "S1 3"]  # b of the root rows of the step that ends at t_k
    root_omega: Float[Array, "S1 3"]
    rel_rot: Float[Array, "S1 B 3 3"]  # each body's desired rotation in its parent's frame
    rel_omega: Float[Array, "S1 B 3"]  # desired relative angular velocity, parent frame
    init: State
    # Derived from theta and rel_rot in make_reference, once for the whole grid, so that the
    # step does not rebuild them: they depend on the mocap only, never on the state.
    local_axes: Float[Array, "S1 C 3 3"]  # axes h_i of each joint in its parent's frame (columns)
    rel_quat: Float[Array, "S1 C 4"]  # quaternion of each joint's desired rotation (rel_rot of its child)
    local_pinv: Float[Array, "S1 C 3 3"]  # P_L resolving a parent-frame error along the axes (control.JointAffine)
    # driven joints' rates over the step that ends at t_k (parent frame at its start)
    drive_omega: Float[Array, "S1 B 3"]
    kkt_residual: Float[Array, " S1"]  # relative residual of the feedforward's solve per step
    landing: Float[Array, " S1"]  # rotation (rad) the discrete inverse leaves per step (0: Eq. 3)
    # The discrete inverse's body velocities u_k ([linear, angular], world; None with Eq. 3):
    # the state of the replay at t_k, and the reference's motion for the feedback's drift.
    velocity: Float[Array, "S1 B 6"] | None = None

    def pose_targets(self, k) -> PoseTargets:
        """What post-stabilization projects onto at grid step k (the driven root and joints)."""
        return PoseTargets(self.root_origin[k], self.root_rot[k], self.rel_rot[k])

    def drift(self, model: Model, k, h: float) -> Float[Array, "C 9"] | None:
        """The reference's motion over step k per joint (:func:`stiffness.reference_drift`)."""
        if self.velocity is None:
            return None
        c, p = model.topology.child, model.topology.parent
        w0, w1 = self.velocity[k, :, 3:], self.velocity[k + 1, :, 3:]
        return jnp.concatenate([h * w1[p], h * w1[c], (w1[c] - w1[p]) - (w0[c] - w0[p])], -1)


def make_reference(model: Model, traj: Trajectory, t0: float | Array, cfg: StepOptions) -> Reference:
    """Sample the mocap targets on the simulation grid of ``cfg`` (h, steps), with the feedforward
    of ``cfg.feedforward`` (the discrete inverse of ``cfg``'s step, or Eq. 3) and the joint axes
    of ``cfg.joint_law``."""
    t0 = jnp.asarray(t0, jnp.float64)
    landed = None
    if Feedforward(cfg.feedforward) is Feedforward.DISCRETE:
        landed = landing_velocities(model, cfg, *_capture_grid(model, traj, t0, cfg))
    return _make_reference(model, traj, t0, cfg, landed)


@functools.partial(compiler.jit, static_argnames=("cfg",))
def _capture_grid(model: Model, traj: Trajectory, t0, cfg: StepOptions):
    """The capture's poses on the grid and the pose targets post-stabilization reads."""
    times = t0 + cfg.h * jnp.arange(cfg.n_steps + 1)
    q = jax.vmap(traj.q)(times)
    pos, rot, *_ = jax.vmap(lambda a: body_kinematics(model, a, a * 0, a * 0))(q)
    rel = jnp.swapaxes(rot[:, model.topology.parent0], -1, -2) @ rot
    origin = pos[:, 0] - jnp.einsum("tij,j->ti", rot[:, 0], model.com[0])
    return pos, matrix_to_quat(rot), PoseTargets(origin, rot[:, 0], rel)


def _reference_feedforward(
    model: Model, traj: Trajectory, cfg: StepOptions, times, kin, rel, root_origin, local_axes, landed
):
    """The feedforward of :func:`_make_reference` by ``cfg.feedforward`` and what it lands on:
    torques, residuals, landing errors, the root's velocity, the reference's angular velocities,
    the stored velocities (discrete), the joints' relative rates and the driven joints' rates."""
    pos, rot, quat, vel, omega, qd = kin
    par = model.topology.parent0
    if Feedforward(cfg.feedforward) is Feedforward.CONTINUOUS:
        sol = inverse_dynamics(model, traj, times, local_axes)
        tau, residual, landing = sol.tau, sol.residual, jnp.zeros_like(times)
        root_vel, ref_omega, stored = qd[:, 0:3], omega, None
        rel_w = jnp.einsum("tbji,tbj->tbi", rot[:, par], omega - omega[:, par])
        drive = rel_w
    else:
        active = dofs_to_per_joint(model, active_mask(model, cfg.driven, rot.dtype))
        targets = PoseTargets(root_origin, rot[:, 0], rel)
        sol = discrete_inverse_dynamics(
            model, cfg, pos, quat, jnp.concatenate([vel[0], omega[0]], -1), targets, local_axes, active, landed
        )
        last = lambda a: jnp.concatenate([a, a[-1:]], 0)
        tau, residual, landing = last(sol.tau), last(sol.residual), last(sol.landing)
        u = stored = sol.velocity
        ref_omega = u[:, :, 3:]
        rel_w = jnp.einsum("tbji,tbj->tbi", rot[:, par], ref_omega - ref_omega[:, par])
        # The root's b and the driven joints' rates of step k-1 -> k, with the levers and the
        # parent frames at that step's start (as the step reads them).
        lever = jnp.einsum("tij,j->ti", rot[:-1, 0], -model.com[0])
        root_vel = jnp.concatenate([qd[:1, 0:3], u[1:, 0, :3] - jnp.cross(lever, u[1:, 0, 3:])], 0)
        drive_next = jnp.einsum("tbji,tbj->tbi", rot[:-1, par], ref_omega[1:] - ref_omega[1:, par])
        drive = jnp.concatenate([rel_w[:1], drive_next], 0)
    return tau, residual, landing, root_vel, ref_omega, stored, rel_w, drive


# One compiled program rather than hundreds of eagerly dispatched small ops (each eager op is
# compiled on its own, which made preparing a run take longer than compiling the rollout).
@functools.partial(compiler.jit, static_argnames=("cfg",))
def _make_reference(model: Model, traj: Trajectory, t0, cfg: StepOptions, landed=None) -> Reference:
    times = t0 + cfg.h * jnp.arange(cfg.n_steps + 1)
    q = jax.vmap(traj.q)(times)
    qd = jax.vmap(traj.qd)(times)
    qdd = jax.vmap(traj.qdd)(times)
    kin = jax.vmap(lambda a, b, c: body_kinematics(model, a, b, c))(q, qd, qdd)
    pos, rot, vel, omega = kin[0], kin[1], kin[2], kin[3]
    quat = matrix_to_quat(rot)
    topo = model.topology
    cols = sim_columns(model)
    theta = jax.vmap(lambda a, t: joint_angles_from_q(model, a, traj.angle_reference(t)))(q, times)[:, cols]
    if JointLaw(cfg.joint_law) is JointLaw.EULER:
        local_axes = jax.vmap(lambda th: joint_local_axes(model, th))(theta)
        local_pinv = damped_pinv(local_axes)
    else:  # the rotation law: each joint's torque and error in its parent's frame
        local_axes = jnp.broadcast_to(jnp.eye(3), (times.shape[0], model.n_bodies - 1, 3, 3))
        local_pinv = local_axes
    par = topo.parent0
    rel = jnp.swapaxes(rot[:, par], -1, -2) @ rot
    root_origin = pos[:, 0] - jnp.einsum("tij,j->ti", rot[:, 0], model.com[0])
    tau, residual, landing, root_vel, ref_omega, stored, rel_w, drive = _reference_feedforward(
        model, traj, cfg, times, (pos, rot, quat, vel, omega, qd), rel, root_origin, local_axes, landed
    )
    # Euler rates from sum_i h_i thetadot_i = omega_child - omega_parent (exact, and much
    # cheaper to compile than a jvp through the Euler decomposition).
    euler_axes_world = jax.vmap(lambda r, th: dof_axes(model, r, th))(rot, theta)
    theta_dot = jax.vmap(lambda ax, w: joint_rates(model, ax, w))(euler_axes_world, ref_omega)
    axes_rows = per_joint_to_dofs(model, jnp.moveaxis(jnp.swapaxes(local_axes, -1, -2), 0, 2))  # (n, T, 3)
    activation = joint_torque_magnitude(model, jnp.moveaxis(axes_rows, 0, 1), tau)
    init = State(pos[0], quat[0], vel[0], omega[0])
    rel_quat = matrix_to_quat(rel[:, topo.child])
    return Reference(
        times,
        tau,
        activation,
        theta,
        theta_dot,
        root_origin,
        rot[:, 0],
        root_vel,
        ref_omega[:, 0],
        rel,
        rel_w,
        init,
        local_axes,
        rel_quat,
        local_pinv,
        drive,
        residual,
        landing,
        stored,
    )


# ---------------------------------------------------------------- the step's three pytrees


class SimModel(eqx.Module):
    """What stays fixed over a rollout: skeleton, mocap reference on the grid, static options."""

    model: Model
    ref: Reference
    options: StepOptions


class Params(eqx.Module):
    """What a user fits or sweeps: the controller's gains and the perturbation pulses."""

    gains: Gains
    pulses: ForcePulses


class StepInfo(eqx.Module):
    """Diagnostics of one step."""

    residual: Float[Array, ""]  # relative residual of the KKT solve of Eq. 2
    violation: Float[Array, ""]  # max |C(x)| after post-stabilization (m or rad)
    force: Float[Array, "B 3"]  # perturbation force per body (world, N)
    points: Float[Array, "P 3"]  # world application points of the pulses
    lam: Float[Array, " nc"]  # constraint forces (rows of system.full_constraints)
    reflex: Float[Array, "C 3"] | None = None  # the delayed reflex's r_i per joint and DOF (N m); None: no reflex


class Data(eqx.Module):
    """What a step advances: the grid index, the state at t_k, and the last step's diagnostics."""

    k: Int[Array, ""]
    state: State
    info: StepInfo
    history: History | None = None  # the reflex's error history (neuromotor.physics.reflex)
    posture: Posture | None = None  # the balance loop's carry (neuromotor.physics.balance)

    def badness(self, max_speed: float) -> Float[Array, " B"]:
        """Per body: speed over ``max_speed`` (> 1: diverged), inf where not finite."""
        return badness(self.state, max_speed)

    def held(self, last: Data, bad) -> Data:
        """Itself, or after a blow-up (``bad``) with ``last``'s state, so that NaNs do not
        spread through a batch."""
        return eqx.tree_at(lambda d: d.state, self, hold(last.state, self.state, bad))


def init_data(sim: SimModel, params: Params) -> Data:
    """Data at t_0: the reference's initial state, zero diagnostics."""
    model, cfg, state = sim.model, sim.options, sim.ref.init
    if params.pulses.base_velocity is not None:  # a base motion already moving at t_0
        state = dataclasses.replace(state, vel=state.vel + params.pulses.base_velocity[0])
    _, force, points = pulse_wrenches(params.pulses, sim.ref.time[0], model.n_bodies, state.pos, state.rot, model.com)
    zero = jnp.zeros((), state.pos.dtype)
    lam = jnp.zeros(constraint_count(model, cfg.driven, cfg.free_root), state.pos.dtype)
    reflex, balance = params.gains.reflex, params.gains.balance
    posture = None if balance is None else empty_posture(balance, state.pos.dtype)
    if reflex is None:
        return Data(jnp.asarray(0), state, StepInfo(zero, zero, force, points, lam), None, posture)
    n_joints = model.n_bodies - 1
    history = empty_history(reflex, n_joints, state.pos.dtype)
    info = StepInfo(zero, zero, force, points, lam, jnp.zeros((n_joints, 3), state.pos.dtype))
    return Data(jnp.asarray(0), state, info, history, posture)


def data_at(sim: SimModel, params: Params, k, state: State) -> Data:
    """Data at grid step k holding ``state`` (zero diagnostics): one step from any state."""
    return dataclasses.replace(init_data(sim, params), k=jnp.asarray(k), state=state)


# ---------------------------------------------------------------- stages


def active_mask(model: Model, driven: tuple[int, ...], dtype) -> Float[Array, " n"]:
    """1 on the DOFs whose muscle torque is applied, 0 on those of driven joints."""
    return jnp.array([0.0 if b in driven else 1.0 for b in model.dof_body], dtype)


def reference_inputs(sim: SimModel, gains: Gains, k) -> ControllerInputs:
    """Stage 1: what the controller reads from the mocap at grid step k, per joint."""
    ref, model = sim.ref, sim.model
    active = active_mask(model, sim.options.driven, ref.tau.dtype)
    return controller_inputs(
        model,
        gains,
        active,
        ref.tau[k],
        ref.activation[k],
        ref.theta[k],
        ref.rel_rot[k],
        ref.rel_omega[k],
        ref.local_axes[k],
        ref.rel_quat[k],
        ref.local_pinv[k],
        ref.drift(model, k, sim.options.h),
    )


def stiff_forces(
    sim: SimModel, gains: Gains, inputs: ControllerInputs, state: State, tree: bool, unrolled: bool = False
) -> StiffBlocks | DenseStiffness:
    """Stage 2: the muscle torques (Eq. 4 and Section 5.2) and the gyroscopic term, with their
    K and D in the representation the solver takes (``unrolled``: the batched solver's form)."""
    model = sim.model
    if not sim.options.implicit:
        return explicit_forces(model, gains, inputs, state, tree)
    if tree:
        return stiff_blocks(model, gains, inputs, state, sim.options.jacobians, unrolled)
    return stiff_jacobians(model, gains, inputs, state.rot, state.omega)


def applied_forces(sim: SimModel, pulses: ForcePulses, k, state: State):
    """Stage 3: gravity and the perturbation pulses, ``(forces (B, 6), per-body force, points)``."""
    model = sim.model
    f_pert, per_body, points = pulse_wrenches(pulses, sim.ref.time[k], model.n_bodies, state.pos, state.rot, model.com)
    return (gravity_forces(model) + f_pert).reshape(-1, 6), per_body, points


def delayed_reflex(sim: SimModel, gains: Gains, inputs: ControllerInputs, state: State, history: History):
    """Stage 3b: this step's angle and rate errors pushed into the history, and the delayed
    reflex (:mod:`neuromotor.physics.reflex`) that joins k of Eq. 2: ``(joint torques (world),
    multipliers r_i per joint and DOF, history)``."""
    topo = sim.model.topology
    rot, omega = state.rot, state.omega
    rot_p = rot[topo.parent]
    axes = mm(rot_p, inputs.local_axes)
    angle, rate = joint_errors(
        rot_p, rot[topo.child], omega[topo.parent], omega[topo.child], inputs.pinv(), inputs.rel_rot, inputs.rel_omega
    )
    history = push(history, angle, rate)
    return *reflex_torque(gains, history, sim.options.h, axes, inputs), history


def momentum_rhs(model: Model, h: float, state: State, inertia, forces, damping_v) -> Float[Array, "B 6"]:
    """Stage 4: the first block row's right-hand side of Eq. 2, ``r = M v + h (k - D v)``."""
    v = state.v.reshape(model.n_bodies, 6)
    return mass_times(model, inertia, v) + h * (forces - damping_v)


class Eq2(eqx.Module):
    """Eq. 2 of one step in the chosen solver's layout (matrix, ``r`` and ``b``), and the
    perturbation pulses it includes (for the step's record)."""

    system: Any
    r: Float[Array, "B 6"]
    b: Float[Array, " nc"]
    force: Float[Array, "B 3"]  # perturbation force per body (world, N)
    points: Float[Array, "P 3"]  # world application points of the pulses
    reflex: Float[Array, "C 3"] | None = None  # the delayed reflex's r_i per joint and DOF (N m along h_i)
    history: History | None = None  # the reflex's error history including this step
    posture: Posture | None = None  # the balance loop's carry including this step


def equations_of_motion(sim: SimModel, params: Params, data: Data, solver: solvers.KKTSolver) -> Eq2:
    """Stages 1 to 5: controller inputs, stiff forces with K and D, applied forces, the
    right-hand side ``(r, b)`` and the solver's assembly of Eq. 2's matrix."""
    model, cfg, ref = sim.model, sim.options, sim.ref
    k, state = data.k, data.state
    rot = state.rot
    inputs = reference_inputs(sim, params.gains, k)
    balance, stepped = params.gains.balance, None
    if balance is not None and balance.stepping is not None:
        # Stepping retargets the legs' reference, so the loop runs before the stiff forces.
        assert data.posture is not None  # init_data gives a balance loop its carry
        stepped = balance_torques(model, balance, state, data.posture, cfg.h, support_motion(sim, params.pulses, k))
        step_state = stepped[1].step
        assert step_state is not None
        rel_rot, rel_quat, rel_omega = swing_reference(
            model, balance, state, step_state, inputs.rel_rot, inputs.rel_quat, inputs.rel_omega
        )
        inputs = dataclasses.replace(inputs, rel_rot=rel_rot, rel_quat=rel_quat, rel_omega=rel_omega)
    stiff = stiff_forces(sim, params.gains, inputs, state, solver.tree_blocks, solver.unrolled)
    applied, per_body, points = applied_forces(sim, params.pulses, k, state)
    reflex, history = None, None
    if params.gains.reflex is not None:
        assert data.history is not None  # init_data gives a reflex its history
        torque, reflex, history = delayed_reflex(sim, params.gains, inputs, state, data.history)
        applied = applied.at[:, 3:].add(body_torques(model, torque))
    posture = None
    if balance is not None:
        applied, posture = balance_stage(sim, balance, params.pulses, k, state, data.posture, applied, stepped)
    inertia = world_inertia(model, rot)
    r = momentum_rhs(
        model,
        cfg.h,
        state,
        inertia,
        applied + stiff.forces(),
        stiff.damping_times(model, state.v.reshape(model.n_bodies, 6)),
    )
    root_vel = ref.root_vel[k + 1]
    if params.pulses.base_velocity is not None:  # the base motion moves the driven root's path
        root_vel = root_vel + params.pulses.base_velocity[k + 1]
    b = constraint_velocity(
        model, cfg.driven, rot, root_vel, ref.root_omega[k + 1], ref.drive_omega[k + 1], cfg.free_root
    )
    system = solver.assemble(model, cfg, rot, inertia, stiff, cfg.h)
    return Eq2(system, r, b, per_body, points, reflex, history, posture)


def balance_stage(sim: SimModel, balance: Balance, pulses: ForcePulses, k, state: State, posture, applied, done=None):
    """Stage 3c: the standing feedforward, the delayed postural loop and the assist
    (:mod:`neuromotor.physics.balance`) added to the applied forces: ``(applied, posture history)``;
    ``done``: the loop's ``(torque, posture)`` when already computed (stepping). The assist pulls
    toward the captured path carried along by a base motion (a platform)."""
    model, ref = sim.model, sim.ref
    assert posture is not None  # init_data gives a balance loop its history
    if done is None:
        torque, posture = balance_torques(model, balance, state, posture, sim.options.h, support_motion(sim, pulses, k))
    else:
        torque, posture = done
    applied = applied.at[:, 3:].add(body_torques(model, torque))
    target, target_vel = assist_target(model, ref, k, pulses.base_offset, pulses.base_velocity)
    applied = applied.at[0, :3].add(assist_force(model, balance, state.pos[0], state.vel[0], target, target_vel))
    return applied, posture


def support_motion(sim: SimModel, pulses: ForcePulses, k):
    """The ground's motion under a free root at the start of step k, for the postural loop's
    lean rate: ``(V_k, Omega_k, the pivot's place c_k)`` (Omega and c None without a tilt), or
    None on a still ground (the program without a platform is unchanged)."""
    if not sim.options.free_root or pulses.base_velocity is None:
        return None
    velocity = pulses.base_velocity[k]
    spin = None if pulses.base_spin is None else pulses.base_spin[k]
    return velocity, spin, pulses.pivot_at(k)


def assist_target(model: Model, ref: Reference, k, base_offset=None, base_velocity=None):
    """``(target, target velocity or None)`` of the assist at grid step ``k`` (an index, or an
    array of them): the pelvis's captured COM, carried along by a base motion's displacement and
    velocity (``base_offset``, ``base_velocity``: (S+1, 3) each, or None)."""
    target = ref.root_origin[k] + ref.root_rot[k] @ model.com[0]
    if base_offset is None:
        return target, None
    assert base_velocity is not None
    return target + base_offset[k], base_velocity[k]


def pose_targets(sim: SimModel, pulses: ForcePulses, k) -> PoseTargets:
    """What post-stabilization projects onto at grid step k: the capture's driven root and
    joints, the root moved by the base motion's displacement when there is one."""
    targets = sim.ref.pose_targets(k)
    if pulses.base_offset is None:
        return targets
    return dataclasses.replace(targets, root_origin=targets.root_origin + pulses.base_offset[k])


def integrate(
    sim: SimModel,
    solver: solvers.KKTSolver,
    k,
    state: State,
    dx: Float[Array, "B 6"],
    v_new: Float[Array, "B 6"],
    pulses: ForcePulses,
) -> tuple[State, Float[Array, ""]]:
    """Stages 7 and 8: positions move by dx (quaternions by the exponential map), then
    post-stabilization onto the targets of t_k+1. The new state (velocity ``v_new``) and the
    constraint violation left."""
    pos, quat = retract(state.pos, state.quat, dx)
    pos, quat, cerr = post_stabilize(sim.model, sim.options, solver, pos, quat, pose_targets(sim, pulses, k + 1))
    violation = jnp.max(jnp.abs(cerr)) if cerr.size else jnp.zeros((), pos.dtype)
    return State(pos, quat, v_new[:, :3], v_new[:, 3:]), violation


def step(sim: SimModel, params: Params, data: Data) -> Data:
    """One linearly implicit step from t_k to t_k + h: Eq. 2 plus post-stabilization."""
    cfg = sim.options
    solver = solvers.get(cfg.solver)
    eq = equations_of_motion(sim, params, data, solver)
    v_new, aux = solver.solve(eq.system, eq.r, eq.b)  # stage 6
    lam, residual = solver.multipliers(eq.system, eq.r, eq.b, v_new, aux)
    new, violation = integrate(sim, solver, data.k, data.state, cfg.h * v_new, v_new, params.pulses)
    info = StepInfo(residual, violation, eq.force, eq.points, lam / cfg.h, eq.reflex)
    return Data(data.k + 1, new, info, eq.history, eq.posture)


# ---------------------------------------------------------------- rollout


class Rollout(eqx.Module):
    """States at t_0..t_S, simulated joint angles, and per-step diagnostics."""

    time: Float[Array, " S1"]
    states: State  # leaves with leading axis S+1
    theta: Float[Array, "S1 n"]
    theta_dot: Float[Array, "S1 n"]
    residual: Float[Array, " S"]
    violation: Float[Array, " S"]
    force: Float[Array, "S1 B 3"]
    points: Float[Array, "S1 P 3"]
    diverged_step: Int[Array, ""]  # -1 if the run stayed finite
    diverged_body: Int[Array, ""]
    reflex: Float[Array, "S1 C 3"] | None = None  # the reflex's r_i per joint and DOF (N m; zero at t_0)


def badness(state: State, max_speed: float) -> Float[Array, " B"]:
    """Per body: the larger of its speed and spin over ``max_speed`` (> 1: diverged), inf where
    any of its state is not finite."""
    finite = (
        jnp.all(jnp.isfinite(state.pos), -1)
        & jnp.all(jnp.isfinite(state.quat), -1)
        & jnp.all(jnp.isfinite(state.vel), -1)
        & jnp.all(jnp.isfinite(state.omega), -1)
    )
    speed = jnp.maximum(jnp.linalg.norm(state.vel, axis=-1), jnp.linalg.norm(state.omega, axis=-1))
    score = jnp.where(finite, speed / max_speed, jnp.inf)
    return score


def observe(model: Model, state: State, ref: Reference, k):
    """Simulated joint angles (on the branch nearest the mocap's) and rates of a state."""
    return joint_angles_and_rates(model, state.quat, state.omega, reference=ref.theta[k])


def hold(last, new, bad):
    """``last`` where ``bad``, else ``new`` (leaf by leaf)."""
    return jax.tree_util.tree_map(lambda a, b: jnp.where(bad, a, b), last, new)


def depending_on(params, carry, skip=None):
    """``carry`` as it is, but traced as a function of every inexact leaf of ``params`` (a
    select that always picks ``carry``; XLA folds it away), except the leaf ``skip`` and any
    boolean leaves.

    ``lax.scan``'s JVP and batching rules find which carries have a tangent or a batch axis by
    iterating to a fixed point, tracing the step again each round. A rollout's state depends on
    the gains and pulses after one step, so starting it as dependent makes the first round the
    last: ``jacfwd``, ``grad`` and ``vmap`` of a rollout trace the step half as often, with the
    same program (docs/benchmarks.md, "Issue 17: one trace per transformation"). The grid index
    is skipped: it does not depend on them, and batched it would turn the reference's slices
    into gathers."""
    leaves = [x for x in jax.tree_util.tree_leaves(params) if eqx.is_inexact_array(x)]
    if not leaves:
        return carry
    zero = sum(jnp.sum(x) for x in leaves) * 0  # unused values: a NaN here cannot reach the carry

    def tie(a):
        if a is skip or not eqx.is_array(a) or not jnp.issubdtype(a.dtype, jnp.number):
            return a
        return jax.lax.select(jnp.ones(a.shape, bool), a, a + zero.astype(a.dtype))

    return jax.tree_util.tree_map(tie, carry)


def scan_steps(sim: SimModel, params: Params, data0, step_fn=step):
    """``sim.options.n_steps`` steps of ``step_fn(sim, params, data) -> data`` from ``data0`` in one
    ``lax.scan``: ``(data stacked over the steps, first diverged step, its body)``. Any data with
    ``k``, ``state``, ``badness`` and ``held`` will do (the contact step's carries a ball too)."""
    cfg = sim.options
    if sim.ref.time.shape[0] < cfg.n_steps + 1:
        raise ValueError(f"reference has {sim.ref.time.shape[0] - 1} steps, config asks for {cfg.n_steps}")

    def body(carry, _):
        data, bad_step, bad_body = carry
        new = step_fn(sim, params, data)
        score = new.badness(cfg.max_speed)
        first = (jnp.max(score) > 1.0) & (bad_step < 0)
        bad_step = jnp.where(first, data.k, bad_step)
        bad_body = jnp.where(first, jnp.argmax(score), bad_body)
        new = new.held(data, bad_step >= 0)
        return (new, bad_step, bad_body), new

    init = depending_on(params, (data0, jnp.asarray(-1), jnp.asarray(-1)), skip=data0.k)
    (_, bad_step, bad_body), out = jax.lax.scan(body, init, None, length=cfg.n_steps)
    return out, bad_step, bad_body


def rollout_of(sim: SimModel, data0, out, bad_step, bad_body) -> Rollout:
    """The :class:`Rollout` of :func:`scan_steps`' output: states from t_0, their joint angles
    and rates, and the steps' diagnostics."""
    model, ref, n_steps = sim.model, sim.ref, sim.options.n_steps
    stack = lambda a, b: jnp.concatenate([a[None], b], 0)
    states = jax.tree_util.tree_map(stack, data0.state, out.state)
    # Joint angles and rates of all states at once after the scan: the per-step loop keeps
    # only the dynamics, and the observation runs as a few wide vectorized ops.
    theta, theta_dot = jax.vmap(lambda st, k: observe(model, st, ref, k))(states, jnp.arange(n_steps + 1))
    return Rollout(
        ref.time[: n_steps + 1],
        states,
        theta,
        theta_dot,
        out.info.residual,
        out.info.violation,
        stack(data0.info.force, out.info.force),
        stack(data0.info.points, out.info.points),
        bad_step,
        bad_body,
        None if out.info.reflex is None else stack(data0.info.reflex, out.info.reflex),
    )


def simulate(sim: SimModel, params: Params) -> Rollout:
    """``sim.options.n_steps`` steps of :func:`step` from the reference's initial state (one ``lax.scan``),
    in the precision ``sim.options.dtype`` (the model, reference and parameters are cast to it)."""
    sim, params = cast((sim, params), sim.options.dtype)
    data0 = init_data(sim, params)
    return rollout_of(sim, data0, *scan_steps(sim, params, data0))


def rollout(model: Model, gains: Gains, pulses: ForcePulses | None, ref: Reference, options: StepOptions) -> Rollout:
    """A convenience for users: ``simulate(SimModel(model, ref, options), Params(gains, pulses))``
    (``pulses`` None: none). The package itself calls :func:`simulate`, the one way to run."""
    return simulate(SimModel(model, ref, options), Params(gains, no_pulses() if pulses is None else pulses))


def check_rollout(model: Model, run: Rollout) -> Rollout:
    """Raise :class:`SimulationDiverged` (step, time, body) if the rollout blew up."""
    step_ = int(run.diverged_step)
    if step_ >= 0:
        raise SimulationDiverged(step_, float(run.time[step_ + 1]), model.body_names[int(run.diverged_body)])
    return run
