"""Issue 38: a run on the ground does not depend on the capture's frame or unit. The embedded
clip and a copy of it turned to Z up, turned 37 deg about the vertical and written in inches
(another world, the same motion) give the same free-root run under a push, and the shipped
walk and such a copy the same ground reaction forces of the contact-aware inverse.

The friction polygons (the ground LCP's and the inverse's pyramid) used to lie along the world's
axes, so they turned against the character with the capture: a push's figures differed by up to
0.4 % between the two copies and the walk's ground forces by 1.5 N. Now their first edge follows
each body's own forward axis (``Ground.axes``), so they also turn with a foot that turns."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import SHARED_MOCAP
from scipy.spatial.transform import Rotation

from neuromotor.config import simulation_config
from neuromotor.model.bvh import read_bvh, write_bvh
from neuromotor.model.load import default_clip_path, load_character
from neuromotor.physics.dynamics import StepOptions, make_reference
from neuromotor.studies import residuals as rs
from neuromotor.studies.balance import facing_axes
from neuromotor.studies.simulate import prepare, run

TURN = Rotation.from_euler("z", 37, degrees=True).as_matrix() @ Rotation.from_euler("x", 90, degrees=True).as_matrix()
WALK = "walk_22joint_zyx.bvh"


def turned_copy(src, dst, metres_per_unit: float):
    """``src`` with its root's translation and rotation turned by TURN, written in another unit."""
    raw = read_bvh(src)
    root, motion = raw.joints[0], raw.motion.copy()
    cols, rcols, order = list(root.translation_columns), list(root.rotation_columns), root.rotation_order
    motion[:, cols] = motion[:, cols] @ TURN.T
    rot = Rotation.from_euler(order, motion[:, rcols], degrees=True).as_matrix()
    motion[:, rcols] = Rotation.from_matrix(TURN @ rot).as_euler(order, degrees=True)
    write_bvh(dst, dataclasses.replace(raw, motion=motion, length_scale=metres_per_unit))
    return dst


def test_a_push_on_the_ground_does_not_depend_on_the_frame_or_unit(tmp_path):
    push = {"body": "pelvis", "direction": "backward", "magnitude": 188.0, "start": 0.3, "duration": 0.1,
            "shape": "half_sine"}
    sim = {"root": "free", "still": 12.567, "duration": 1.0, "h": 1.0 / 120.0}
    runs = []
    for clip in (default_clip_path(), turned_copy(default_clip_path(), tmp_path / "turned_in.bvh", 0.0254)):
        setup = prepare(simulation_config({"clip": str(clip), "sim": sim, "perturbation": [push]}, "<test>"))
        runs.append((setup, run(setup)))
    (a, ra), (b, rb) = runs
    assert a.character.anatomy.units != b.character.anatomy.units and b.character.anatomy.up_axis == 2
    np.testing.assert_allclose(np.asarray(b.ground.axes), np.asarray(a.ground.axes), atol=1e-6)  # in each body
    np.testing.assert_allclose(np.asarray(rb.perturbed.states.pos), np.asarray(ra.perturbed.states.pos) @ TURN.T,
                               rtol=0, atol=1e-6)
    assert ra.metrics["sway_range_ap_mm"] > 20.0 and not ra.metrics["fell"]  # the push moves the body
    for key in ("peak_deviation_deg", "final_error_deg", "unperturbed_rms_error_deg", "sway_rms_mm",
                "sway_range_ap_mm", "sway_range_ml_mm", "ground_peak_force_N", "lcp_residual_p95_mps"):
        assert rb.metrics[key] == pytest.approx(ra.metrics[key], rel=1e-6), key
    assert (rb.metrics["fell"], rb.metrics["ground_contact_fraction"]) == (ra.metrics["fell"],
                                                                          ra.metrics["ground_contact_fraction"])


def test_ground_reaction_forces_do_not_depend_on_the_frame_or_unit(tmp_path):
    forces = []
    for clip in (SHARED_MOCAP / WALK, turned_copy(SHARED_MOCAP / WALK, tmp_path / "walk_cm.bvh", 0.01)):
        character, traj = load_character(clip)
        options = StepOptions(h=1.0 / 120.0, n_steps=240)  # 2 s of walking from 3.5 s
        ref = make_reference(character.model, traj, 3.5, options)
        res = rs.capture_residuals(character, traj, ref, options)
        forces.append((res.ground.force, res.residual))
    (fa, ra), (fb, rb) = forces
    assert np.abs(fa).max() > 100.0
    np.testing.assert_allclose(fb, fa @ TURN.T, rtol=0, atol=1e-3)  # N
    np.testing.assert_allclose(rb[:, :3], ra[:, :3] @ TURN.T, rtol=0, atol=1e-3)  # N
    np.testing.assert_allclose(rb[:, 3:], ra[:, 3:] @ TURN.T, rtol=0, atol=1e-3)  # N m


def test_contact_tangents_turn_with_the_scene():
    """The ball's and the ground's contact tangents (facing_basis of up, then the facing or the
    ball's flight) turn with any rotation of the whole scene; the world-axis tangents
    (tangent_basis, what every contact used before) do not."""
    import jax.numpy as jnp

    from neuromotor.physics.contact import facing_basis, tangent_basis

    rng = np.random.default_rng(5)
    up, flight = np.array([0.0, 1.0, 0.0]), np.array([0.3, -0.1, -0.95])
    normals = rng.normal(size=(64, 3))
    normals[:4] = [up, -up, [0.05, 1.0, 0.0], [1.0, 0.0, 0.0]]  # level (ground, top of a head), near level, side
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    turned = Rotation.random(random_state=7).as_matrix()
    t1, t2 = facing_basis(jnp.asarray(normals), jnp.asarray(up), jnp.asarray(flight))
    r1, r2 = facing_basis(jnp.asarray(normals @ turned.T), jnp.asarray(turned @ up), jnp.asarray(turned @ flight))
    np.testing.assert_allclose(np.asarray(r1), np.asarray(t1) @ turned.T, atol=1e-12)
    np.testing.assert_allclose(np.asarray(r2), np.asarray(t2) @ turned.T, atol=1e-12)
    frame = np.stack([normals, np.asarray(t1), np.asarray(t2)], 1)  # right-handed, orthonormal
    np.testing.assert_allclose(frame @ np.swapaxes(frame, 1, 2), np.broadcast_to(np.eye(3), frame.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frame), 1.0, atol=1e-12)
    level = np.asarray(t1)[:2]  # the ground's normal: along the flight's horizontal part
    along = flight - flight @ up * up
    np.testing.assert_allclose(level[0], along / np.linalg.norm(along), atol=1e-12)
    w1, _ = tangent_basis(jnp.asarray(normals @ turned.T))
    assert np.abs(np.asarray(w1) - np.asarray(tangent_basis(jnp.asarray(normals))[0]) @ turned.T).max() > 0.1


def test_a_held_pose_does_not_depend_on_the_frames_it_does_not_hold(tmp_path):
    """A still run of a frame that faces another way than the clip's most upright frame (where
    the anatomy's facing is found): turning every later frame of the clip by 90 deg about the
    vertical turns that facing but not the held pose, so the run, its friction axes and its
    sway along and across the facing are the same (until 2026-11-29 the friction polygons and
    the AP/ML axes followed the turned reference frame: AP and ML swapped)."""
    raw = read_bvh(default_clip_path())
    root, motion = raw.joints[0], raw.motion.copy()
    cols, rcols, order = list(root.translation_columns), list(root.rotation_columns), root.rotation_order
    turn = Rotation.from_euler("y", 90, degrees=True).as_matrix()  # the embedded clip is Y up
    late = motion[300:]
    late[:, cols] = late[:, cols] @ turn.T
    late[:, rcols] = Rotation.from_matrix(turn @ Rotation.from_euler(order, late[:, rcols], degrees=True)
                                          .as_matrix()).as_euler(order, degrees=True)
    motion[300:] = late
    turned = tmp_path / "turned_late.bvh"
    write_bvh(turned, dataclasses.replace(raw, motion=motion))
    push = {"body": "pelvis", "direction": "left", "magnitude": 120.0, "start": 0.2, "duration": 0.1,
            "shape": "half_sine"}
    sim = {"root": "free", "still": 1.5, "duration": 0.6, "h": 1.0 / 120.0}
    setups = [prepare(simulation_config({"clip": str(c), "sim": sim, "perturbation": [push]}, "<test>"))
              for c in (default_clip_path(), turned)]
    a, b = setups
    ref_frame = a.character.anatomy.reference_frame
    assert ref_frame >= 300 and ref_frame == b.character.anatomy.reference_frame  # the facing's frame turned
    assert abs(np.asarray(a.character.anatomy.forward) @ np.asarray(b.character.anatomy.forward)) < 0.1
    np.testing.assert_allclose(facing_axes(b)[1], facing_axes(a)[1], atol=1e-9)
    np.testing.assert_allclose(np.asarray(b.ground.axes), np.asarray(a.ground.axes), atol=1e-9)
    ra, rb = run(a), run(b)
    np.testing.assert_allclose(np.asarray(rb.perturbed.states.pos), np.asarray(ra.perturbed.states.pos), atol=1e-9)
    assert ra.metrics["sway_range_ml_mm"] > 1.4 * ra.metrics["sway_range_ap_mm"]  # a push to the left (17 mm, 12)
    for key in ("sway_range_ap_mm", "sway_range_ml_mm", "sway_rms_mm"):
        assert rb.metrics[key] == pytest.approx(ra.metrics[key], rel=1e-9), key
