"""Contact as a linear complementarity problem (LCP): a flying ball, and the ground under the bodies.

Section 4 of the paper handles contact as an LCP at the velocity level, together with the joint
constraints (Cline 2002). This package adds to the linearly implicit step of Eq. 2 one free
rigid ball (its contacts with the character's bodies and with the ground plane) and the
bodies' own contacts with the ground plane, all solved as one LCP in the same step. One job
per module:

* :mod:`.ball` -- the ball (a solid sphere, every parameter an array leaf) and its state;
* :mod:`.shapes` -- collision capsules fitted to the bodies' polyhedra;
* :mod:`.detection` -- gaps, normals and tangent frames of the ball's candidates (capsules, ground);
* :mod:`.ground` -- the ground plane and the bodies' contact points on it (their polyhedra's lowest vertices);
* :mod:`.lcp` -- projected Gauss-Seidel for the LCP and for the gap projection;
* :mod:`.step` -- the contact step: the ordinary step plus contact rows, in named stages;
* :mod:`.rollout` -- the scan over steps with the ball's state (if any) beside the character's.

The ball's place in a run (building it from a config, aiming, RUN.npz arrays, speed sweeps)
is :mod:`neuromotor.studies.ball_hit`; docs/contact.md describes the physics.
"""

from neuromotor.physics.contact.ball import Ball, BallState, initial_ball_state, make_ball, never_launched
from neuromotor.physics.contact.detection import (
    ContactSettings,
    candidate_bodies,
    candidate_names,
    detect,
    facing_basis,
    on_character,
    tangent_basis,
)
from neuromotor.physics.contact.ground import Ground, GroundSlots, ground_slots, lowest_points, make_ground, vertex_gap
from neuromotor.physics.contact.lcp import lcp_residual, project_polygon, solve_gap_projection, solve_lcp_pgs
from neuromotor.physics.contact.rollout import (
    ContactRollout,
    batched_simulate_contact,
    check_contact_rollout,
    simulate_contact,
    simulate_contact_jit,
)
from neuromotor.physics.contact.shapes import Capsules, fit_capsules, segment_distances
from neuromotor.physics.contact.step import (
    ContactData,
    ContactInfo,
    ContactScene,
    contact_step,
    scene_candidate_bodies,
    scene_candidate_names,
    scene_gaps,
)

__all__ = [
    "Ball",
    "BallState",
    "Capsules",
    "ContactData",
    "ContactInfo",
    "ContactRollout",
    "ContactScene",
    "ContactSettings",
    "Ground",
    "GroundSlots",
    "batched_simulate_contact",
    "candidate_bodies",
    "candidate_names",
    "check_contact_rollout",
    "contact_step",
    "detect",
    "facing_basis",
    "on_character",
    "fit_capsules",
    "ground_slots",
    "initial_ball_state",
    "lcp_residual",
    "lowest_points",
    "make_ground",
    "make_ball",
    "never_launched",
    "project_polygon",
    "scene_candidate_bodies",
    "scene_candidate_names",
    "scene_gaps",
    "segment_distances",
    "simulate_contact",
    "simulate_contact_jit",
    "solve_gap_projection",
    "solve_lcp_pgs",
    "tangent_basis",
    "vertex_gap",
]
