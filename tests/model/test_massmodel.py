"""The anthropometric body model on every shipped clip: stature, body mass, de Leva segment
shares, left/right symmetry, independence of the up axis, shapes a person would recognise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import ALL_CLIPS
from neuromotor.model import deleva
from neuromotor.model import polyhedron as poly
from neuromotor.model.anatomy import prepare_clip
from neuromotor.model.massmodel import LIMB_SHAPE, world_frames
from neuromotor.model.skeleton import MassModelOptions, build_character, joint_offsets, scale_masses

CLIPS = list(ALL_CLIPS.values())


def test_the_shared_clips_are_there():
    assert len(CLIPS) >= 4, "CI must have ../shared/mocap beside the repository"


def character_of(path, **kw):
    options = MassModelOptions(**{k: kw.pop(k) for k in list(kw) if k in ("body_mass", "sex", "simulate_extremities")})
    clip, anatomy, source = prepare_clip(path, **kw)
    return build_character(clip, options, anatomy=anatomy, source_clip=source)


@pytest.fixture(scope="module", params=CLIPS, ids=lambda p: p.stem)
def character(request):
    return character_of(request.param)


def segment_masses(ch) -> dict[tuple[str, str], float]:
    out: dict = {}
    anat, model = ch.anatomy, ch.model
    for b, k in enumerate(model.body_joint):
        seg = ch.body_segment[b]
        side = anat.side[k] if seg not in ("trunk", "head") else ""
        out[(seg, side)] = out.get((seg, side), 0.0) + float(model.mass[b])
    return out


def test_stature_and_body_mass_are_plausible(character):
    h = character.anatomy.stature
    m = float(np.sum(character.model.mass))
    assert 1.3 <= h <= 2.1
    assert 18.5 * h * h <= m <= 30.0 * h * h
    np.testing.assert_allclose(m, deleva.DEFAULT_BMI * h * h, rtol=1e-9)


def test_every_segment_within_its_de_leva_share_and_sides_equal(character):
    total = float(np.sum(character.model.mass))
    fractions = deleva.mass_fractions("average")
    got = segment_masses(character)
    for seg in fractions:
        sides = ("",) if seg in ("trunk", "head") else ("left", "right")
        for side in sides:
            assert (seg, side) in got, f"no {side} {seg} body"
            ratio = got[(seg, side)] / (fractions[seg] * total)
            assert 0.6 <= ratio <= 1.67, (seg, side, ratio)
        if len(sides) == 2:
            np.testing.assert_allclose(got[(seg, "left")], got[(seg, "right")], rtol=1e-6)


def test_limb_com_and_radii_of_gyration_near_de_leva(character):
    anat, model = character.anatomy, character.model
    offsets = joint_offsets(character.clip)
    for b, k in enumerate(model.body_joint):
        seg = anat.segment[k]
        if seg not in LIMB_SHAPE:
            continue
        kids = [c for c, p in enumerate(model.joint_parent) if p == k and model.joint_body[c] >= 0]
        if not kids:
            continue
        bone = offsets[max(kids, key=lambda c: np.linalg.norm(offsets[c]))]
        length = float(np.linalg.norm(bone))
        ref = deleva.segment_parameters(seg)
        along = float(np.dot(np.asarray(model.com[b]), bone)) / length**2
        assert abs(along - ref.com) < 0.06, (seg, along, ref.com)
        inertia = np.asarray(model.inertia[b])
        axis = bone / length
        i_long = axis @ inertia @ axis
        i_trans = 0.5 * (np.trace(inertia) - i_long)
        m = float(model.mass[b])
        r_long, r_trans = np.sqrt(i_long / m) / length, np.sqrt(i_trans / m) / length
        assert 0.6 < r_trans / (0.5 * (ref.r_sagittal + ref.r_transverse)) < 1.4, (seg, r_trans)
        assert 0.5 < r_long / ref.r_longitudinal < 2.0, (seg, r_long)


def test_hands_feet_and_head_exist_even_with_zero_length_end_sites(character):
    anat, model = character.anatomy, character.model
    for seg in ("hand", "foot"):
        for side in ("left", "right"):
            assert any(anat.segment[k] == seg and anat.side[k] == side for k in model.body_joint)
    assert any(anat.segment[k] == "head" for k in model.body_joint)


def test_shapes_look_human(character):
    """Flat hands and feet (thinner than wide), feet with soles near the floor in the pose the
    shapes are built on, a head above the shoulders."""
    anat, model, clip = character.anatomy, character.model, character.clip
    pos, rot = world_frames(clip, joint_offsets(clip), anat.shape_frame)
    up = anat.shape_up
    low = np.inf
    for b, k in enumerate(model.body_joint):
        verts = character.shapes[b].vertices
        world = pos[k] + verts @ rot[k].T
        low = min(low, float((world @ up).min()))
        if anat.segment[k] == "hand":
            centred = verts - verts.mean(0)
            sv = np.linalg.svd(centred, compute_uv=False)
            assert sv[2] < 0.6 * sv[1], (clip.joints[k].name, sv)
        if anat.segment[k] == "foot":  # a flat sole: four or more vertices on the lowest plane
            height = world @ up
            assert np.sum(height < height.min() + 1e-6) >= 4, clip.joints[k].name
    head = [k for k in model.body_joint if anat.segment[k] == "head"][-1]
    b = model.joint_body[head]
    top = float((pos[head] + character.shapes[b].vertices @ rot[head].T).max(0) @ up)
    assert 0.75 * anat.stature < top - low < 1.25 * anat.stature


def test_z_up_copy_gives_the_same_masses_and_angles(character):
    """Rotate the whole capture to Z-up (root position and rotation): same bodies and masses,
    the joint-angle motion untouched, gravity along -Z."""
    from neuromotor.model.bvh import write_bvh
    from neuromotor.rotations_np import euler_to_matrix
    from neuromotor.rotations import matrix_to_euler
    import jax.numpy as jnp
    import tempfile, pathlib

    src = character.source
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # +90 deg about X: Y -> Z
    motion = np.array(src.motion)
    root = src.joints[0]
    tcols, rcols = list(root.translation_columns), list(root.rotation_columns)
    motion[:, tcols] = motion[:, tcols] @ turn.T
    mats = np.stack([turn @ euler_to_matrix(np.deg2rad(r), root.rotation_order) for r in motion[:, rcols]])
    ang = np.asarray(matrix_to_euler(jnp.asarray(mats), root.rotation_order, jnp.deg2rad(jnp.asarray(motion[:, rcols]))))
    motion[:, rcols] = np.rad2deg(ang)
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "zup.bvh"
        write_bvh(path, dataclasses.replace(src, motion=motion), precision=10)
        other = character_of(path, units=src.length_scale)
    assert other.anatomy.up_axis == 2 and other.anatomy.up[2] > 0
    assert other.model.body_names == character.model.body_names
    # the joint-angle motion is the same to round-off (only the root's channels were turned)
    from neuromotor.model.kinematics import mocap_angles
    np.testing.assert_allclose(mocap_angles(other.model, other.clip), mocap_angles(character.model, character.clip),
                               atol=1e-9)
    np.testing.assert_allclose(np.asarray(other.model.mass), np.asarray(character.model.mass), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(other.model.gravity), [0, 0, -9.81])


def test_body_mass_sex_and_extremity_options():
    path = next(p for p in CLIPS if "cmu" in p.name)  # fingers and thumbs
    base = character_of(path)
    heavy = character_of(path, body_mass=90.0, sex="female")
    np.testing.assert_allclose(float(np.sum(heavy.model.mass)), 90.0, rtol=1e-9)
    thigh = lambda ch: segment_masses(ch)[("thigh", "left")] / float(np.sum(ch.model.mass))
    # (the female column sums to 99.99 %: shares are renormalised to the body mass)
    np.testing.assert_allclose(thigh(heavy), deleva.segment_parameters("thigh", "female").mass, rtol=2e-4)
    fingers = character_of(path, simulate_extremities=True)
    assert fingers.model.n_bodies > base.model.n_bodies
    np.testing.assert_allclose(float(np.sum(fingers.model.mass)), float(np.sum(base.model.mass)), rtol=1e-9)
    # the hand segment (palm + fingers) keeps its share
    np.testing.assert_allclose(segment_masses(fingers)[("hand", "left")], segment_masses(base)[("hand", "left")],
                               rtol=1e-6)


def test_scale_masses_is_differentiable_array_maths():
    import jax
    import jax.numpy as jnp

    ch = character_of(CLIPS[0])
    f = lambda m: jnp.sum(scale_masses(ch.model, body_mass=m).inertia[0])
    g = jax.grad(f)(80.0)
    np.testing.assert_allclose(float(g), float(jnp.sum(ch.model.inertia[0])) / float(jnp.sum(ch.model.mass)),
                               rtol=1e-9)


def test_ellipse_ring_hull_volume_matches_the_elliptic_frustum():
    """Hull of two parallel regular-polygon ellipse rings = a polygonal frustum: V = h/3 (A0 + sqrt(A0 A1) + A1)."""
    n, a, b, h, t = 64, 0.05, 0.03, 0.4, 0.6
    u, v = np.eye(3)[0], np.eye(3)[1]
    pts = np.concatenate([poly.ellipse_ring([0, 0, 0], u, v, a, b, n), poly.ellipse_ring([0, 0, h], u, v, t * a, t * b, n)])
    m, com, _ = poly.mass_properties(poly.convex_hull(pts), 1.0)
    area = 0.5 * n * np.sin(2 * np.pi / n) * a * b
    np.testing.assert_allclose(m, h / 3 * area * (1 + t + t * t), rtol=1e-9)
    np.testing.assert_allclose(com[2], h * (1 + 2 * t + 3 * t * t) / (4 * (1 + t + t * t)), rtol=1e-9)


@pytest.mark.parametrize("seed", range(12))
def test_synthetic_rigs_get_a_plausible_symmetric_body(seed, tmp_path):
    """Random rigs (random names, extra leaves, fingers, toes, faces, units, Y- or Z-up, zero-length
    End Sites, 6-channel joints, a ground-marker root, a bent zero pose): a plausible adult whose
    segments have their de Leva shares, equal on both sides, and the same masses when the rig is
    turned Z-up <-> Y-up."""
    from synthetic_rigs import make_rig

    masses = []
    for up in ("Y", "Z"):
        rig = make_rig(seed, up=up)
        path = tmp_path / f"rig_{up}.bvh"
        path.write_text(rig.text)
        ch = character_of(path)
        h, total = ch.anatomy.stature, float(np.sum(ch.model.mass))
        assert 1.3 <= h <= 2.1 and 18.5 * h * h <= total <= 30.0 * h * h
        np.testing.assert_allclose(h, rig.stature, rtol=0.08)
        got = segment_masses(ch)
        for seg, frac in deleva.mass_fractions().items():
            for side in (("",) if seg in ("trunk", "head") else ("left", "right")):
                assert 0.6 <= got[(seg, side)] / (frac * total) <= 1.67, (seg, side)
            if seg not in ("trunk", "head"):
                np.testing.assert_allclose(got[(seg, "left")], got[(seg, "right")], rtol=1e-6)
        masses.append(np.sort(np.asarray(ch.model.mass)))
    np.testing.assert_allclose(masses[0], masses[1], rtol=1e-6)


def test_the_default_hit_finds_its_body_on_every_clip(character):
    """`neuromotor bench CLIP` and `simulate --clip` use the default hit on any rig: its body is
    the segment keyword `chest`, the trunk body the arms hang from (Chest2 on the embedded clip)."""
    from neuromotor.config import DEFAULT_HIT
    from neuromotor.studies.simulate import body_lookup

    b = body_lookup(character.model, "<t>", character)(DEFAULT_HIT["body"])
    k = character.model.body_joint[b]
    assert character.anatomy.segment[k] == "trunk"
    arms = [j for j, s in enumerate(character.anatomy.segment) if s == "upper_arm"]
    for j in arms:  # an ancestor of both upper arms
        while j >= 0 and j != k:
            j = character.model.joint_parent[j]
        assert j == k
    if character.clip.joints[0].name == "Hips" and "Chest2" in character.model.body_names:
        assert character.model.body_names[b] == "Chest2"
