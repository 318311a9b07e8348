"""The ground under the character in a run (issue 38): the ``[ground]`` table made into a
:class:`~neuromotor.physics.contact.Ground` (its default height the floor of the motion the run
follows), the contact rollouts of a run whose bodies touch it, and its part of RUN.npz.

The physics (the plane, the contact points, the LCP rows) is
:mod:`neuromotor.physics.contact.ground` and :mod:`neuromotor.physics.contact.step`;
:mod:`neuromotor.studies.simulate` calls this module for a config whose bodies touch the ground
(``[sim] root = "free"``, or ``[ground] enabled = true``).
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from neuromotor import compiler
from neuromotor.model.kinematics import Trajectory, grid_poses, grid_poses_jit
from neuromotor.model.skeleton import Character, Model
from neuromotor.physics.balance import whole_com
from neuromotor.physics.contact import (
    ContactRollout,
    ContactScene,
    ContactSettings,
    Ground,
    check_contact_rollout,
    lowest_points,
    make_ground,
    simulate_contact_jit,
)
from neuromotor.physics.contact.detection import up_direction
from neuromotor.physics.contact.ground import DEFAULT_PGS_ITERATIONS
from neuromotor.physics.dynamics import Params

FOOT = "foot"  # the mass model's segment of the feet (Character.body_segment)


def labelled_feet(character: Character) -> tuple[int, ...]:
    """The bodies the mass model labels ``foot``; empty on a rig without labelled feet."""
    return tuple(b for b, seg in enumerate(character.body_segment) if seg == FOOT)


def foot_bodies(character: Character) -> tuple[int, ...]:
    """The feet (:func:`labelled_feet`); every body on a rig without labelled feet."""
    return labelled_feet(character) or tuple(range(character.model.n_bodies))


def feet_warnings(character: Character, source: str) -> tuple[str, ...]:
    """A warning for a run on the ground of a rig without labelled feet (every body then stands
    in for a foot: the floor and the fall rule; the postural loop is refused); none with feet."""
    if labelled_feet(character):
        return ()
    return (
        f"{source}: the rig has no labelled feet (see neuromotor inspect): every body counts as a "
        "foot for the ground's floor and the fall rule, so falls are found only by the COM's height",
    )


# How far a given ground may sit from the motion's own floor before a run says so (m): inside
# the feet by more than a sole's thickness, or far enough below them to drop the character.
BURIED_WARN_M = 0.02
DROP_WARN_M = 0.10


def height_warnings(character: Character, traj: Trajectory, height: float, source: str) -> tuple[str, ...]:
    """A warning when ``[ground] height`` is far from the floor the motion stands on
    (:func:`capture_floor`): the feet start inside the ground, or the character drops onto it."""
    floor = capture_floor(character, traj)
    if height - floor > BURIED_WARN_M:
        return (
            f"{source}: field 'ground.height' = {height:g} m is {1e3 * (height - floor):.0f} mm above the feet's "
            f"lowest point ({floor:.4f} m): they start inside the ground and are pushed out",
        )
    if floor - height > DROP_WARN_M:
        return (
            f"{source}: field 'ground.height' = {height:g} m is {1e3 * (floor - height):.0f} mm below the feet's "
            f"lowest point ({floor:.4f} m): the character drops onto it",
        )
    return ()


@functools.partial(compiler.jit, static_argnames=("bodies",))
def _lowest_over(model: Model, traj: Trajectory, ground: Ground, times, bodies):
    poses = grid_poses(model, traj, times)
    return jnp.min(lowest_points(model, ground, poses[0], poses[1], bodies))


def capture_floor(character: Character, traj: Trajectory) -> float:
    """The floor of a motion: the height along the up axis (``-gravity``) of the lowest vertex
    of the feet's polyhedra over every frame of the clip, posed by ``traj``. A still run passes
    its held frame's trajectory, so its pose stands on the ground from the first step."""
    clip = character.clip
    probe = make_ground(character.shapes, 0.0)
    times = jnp.arange(clip.n_frames, dtype=jnp.float64) * clip.frame_time
    return float(_lowest_over(character.model, traj, probe, times, foot_bodies(character)))


def ground_setup(spec, character: Character, traj: Trajectory, capture: Trajectory | None = None) -> Ground:
    """The :class:`Ground` of a parsed ``[ground]`` table (:class:`~neuromotor.config.specs.GroundSpec`):
    at ``height``, or at the floor of ``traj`` (:func:`capture_floor`; the run's trajectory: the
    held frame's for a still run) when the table gives none. The friction axes come from the
    clip's own trajectory ``capture`` (None: ``traj``), where the anatomy's facing was found."""
    height = capture_floor(character, traj) if spec.height is None else spec.height
    sweeps = DEFAULT_PGS_ITERATIONS if spec.pgs_iterations is None else spec.pgs_iterations
    return make_ground(
        character.shapes,
        height,
        spec.friction,
        spec.restitution,
        spec.contacts_per_body,
        spec.max_contacts,
        pgs_iterations=sweeps,
        axes=friction_axes(character, traj if capture is None else capture),
    )


def friction_axes(character: Character, traj: Trajectory) -> np.ndarray | None:
    """Each body's forward and left axes in its own frame, ``(B, 2, 3)``: the character's facing
    (``anatomy.forward``) and ``up x forward`` in its most upright pose (``anatomy.reference_frame``),
    carried into every body's frame there. They orient the friction polygon of each body's
    contacts, on the ground and in the capture's ground reaction forces, so the polygon turns
    with the body; None without an anatomy (world axes). ``traj`` must be the clip's own (not a
    held pose's): the facing was found in its reference frame."""
    anatomy = character.anatomy
    if anatomy is None:
        return None
    model = character.model
    forward = np.asarray(anatomy.forward, np.float64)
    left = np.cross(np.asarray(up_direction(model)), forward)
    time = jnp.asarray([anatomy.reference_frame * character.clip.frame_time], jnp.float64)
    rot = np.asarray(grid_poses_jit(model, traj, time)[1][0])  # (B, 3, 3): body to world
    return np.einsum("bji,aj->bai", rot, np.stack([forward, left]))


def ground_scene(ground: Ground, settings: ContactSettings | None = None) -> ContactScene:
    """A contact scene of the ground alone (no ball); ``settings`` None: the defaults with the
    ground's own PGS sweep count (``[ground] pgs_iterations``)."""
    settings = ContactSettings(pgs_iterations=ground.pgs_iterations) if settings is None else settings
    return ContactScene(None, None, settings, ground)


def ground_rollouts(setup, base_pulses, check: bool = True) -> tuple[ContactRollout, ContactRollout]:
    """Perturbed (the config's pulses) and unperturbed (``base_pulses``) contact rollouts of a
    run whose bodies touch the ground (and no ball), with the same compiled function."""
    scene = ground_scene(setup.ground)
    pert = simulate_contact_jit(setup.sim_model, setup.params, scene)
    base = simulate_contact_jit(setup.sim_model, Params(setup.gains, base_pulses), scene)
    if check:
        check_contact_rollout(setup.model, base)
        check_contact_rollout(setup.model, pert)
    return pert, base


def ground_metrics(out: ContactRollout, first: int) -> dict:
    """What the ground adds to a run's metrics (:func:`ground_figures`); ``first``: the index of
    the ground's first candidate."""
    lam = np.asarray(out.contact.normal_impulse)[:, first:]
    return ground_figures(lam.sum(-1), float(out.run.time[1] - out.run.time[0]))


def ground_figures(total, h: float) -> dict:
    """The peak total normal force (N) and the fraction of steps with a contact, of the total
    normal impulse on the ground per step (``total``, (S+1,), row 0 before any step)."""
    total = np.asarray(total)
    return {
        "ground_peak_force_N": float(total.max() / h),
        "ground_contact_fraction": float((total > 0)[1:].mean()),
    }


def lcp_figures(step_residual, touching) -> dict:
    """How well each step's contact LCP was solved (any contact run, the ball's too): the
    largest residual (m/s, :func:`~neuromotor.physics.contact.lcp.lcp_residual`) over the run,
    and the 95th percentile of each step's largest over the steps with a contact (both 0.0 with
    no contact). ``step_residual``, ``touching``: per step, as ``ContactInfo`` gives them."""
    r = np.asarray(step_residual)[np.asarray(touching)]
    if not r.size:
        return {"max_lcp_residual_mps": 0.0, "lcp_residual_p95_mps": 0.0}
    return {"max_lcp_residual_mps": float(r.max()), "lcp_residual_p95_mps": float(np.percentile(r, 95))}


def tilt_pivot(model, ref, ground: Ground | None) -> np.ndarray | None:
    """Where a tilt turns the ground unless its ``pivot`` says otherwise: the ground point under
    the whole-body COM of the run's first pose (world, m; None without a ground)."""
    if ground is None:
        return None
    com, up = np.asarray(whole_com(model, ref.init.pos)), np.asarray(up_direction(model))
    return com - (com @ up - float(ground.height)) * up


def moves_ground(setup) -> bool:
    """Whether a base motion moves the ground (a platform): a free root, a ground, a base motion."""
    return setup.options.free_root and setup.ground is not None and setup.pulses.base_offset is not None


def platform_offset(setup) -> np.ndarray | None:
    """The ground's displacement (S+1, 3) on the grid when a base motion moves it, else None."""
    return np.asarray(setup.pulses.base_offset) if moves_ground(setup) else None


def ground_arrays(setup, out: ContactRollout) -> dict[str, np.ndarray]:
    """The ground's part of RUN.npz: per slot (each body's lowest vertices) ``ground_impulse``
    (T, G, 3, on the body, world), ``ground_normal_impulse`` and ``ground_gap`` (T, G),
    ``ground_body`` (G), and ``ground_height`` (m)."""
    ground: Ground = setup.ground
    first = out.contact.gap.shape[1] - ground.n_slots
    c = out.contact
    return {
        "ground_impulse": np.asarray(c.impulse[:, first:]),
        "ground_normal_impulse": np.asarray(c.normal_impulse[:, first:]),
        "ground_gap": np.asarray(c.gap[:, first:]),
        "ground_body": np.asarray(ground.slot_body),
        "ground_height": np.asarray(float(ground.height)),
    }
