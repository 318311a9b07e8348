"""Anthropometric polyhedra: one convex shape per body, sized so that at the density of water
each segment weighs its de Leva (1996) share of the body mass.

The paper approximates the character "with polyhedra ... assuming the density of water"
(Section 5.1). We keep that, and make the polyhedra look like a person of the clip's size:

* **Body mass** ``M``: given, or ``DEFAULT_BMI * stature^2`` (BMI 22).
* **Segment targets**: ``M`` times de Leva's Table 4 fraction (see :mod:`neuromotor.model.deleva`).
  A segment may be several bodies (a trunk of pelvis, spine, chest and clavicle bodies; a head of
  neck and skull); extremity detail without a body of its own (fingers, toes, face) counts in
  its hand, foot or head. A segment the rig lacks passes its mass to its parent segment (a hand
  to the forearm, a head to the trunk), so the total is always ``M``.
* **Shapes** (every one a convex hull of elliptic rings, in the body's joint frame):
  tapered frustums for upper arms, forearms, thighs and shanks (taper and overhang chosen so the
  COM lies near de Leva's position along the segment); a trunk of elliptic cross-sections from
  below the hip joints to the shoulders, wider at pelvis and chest than at the waist; a head of
  four rings; flat hands along the fingers; flat feet from heel to toe with the sole one ankle
  height below the ankle. Breadths are stature fractions; a head, hand or foot whose End Site
  has zero length gets its anthropometric length along its parent bone's direction.
* **Mass match**: the cross-sections of a segment's bodies are scaled by one factor, found by a
  few fixed-point steps, until their volume at ``density`` gives the segment's target; the mass,
  COM and inertia are then integrated exactly from the polyhedra (:mod:`neuromotor.model.polyhedron`).

The shapes are built in one pose (``Anatomy.shape_frame``): the zero pose (every rotation 0)
when it is a standing pose, so the body depends on the skeleton and the options only, whatever
frames the clip holds; else the clip's most upright frame, so a rig whose zero pose is not a
standing pose (every bone along its joint's X axis) still gets flat feet on the floor. Up, forward
and left for a body are those of that pose (``shape_up``, ``shape_forward``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from neuromotor.errors import UserError
from neuromotor.model import deleva, polyhedron as poly
from neuromotor.model.anatomy import DETAIL_SEGMENTS, Anatomy
from neuromotor.model.bvh import BvhClip
from neuromotor.rotations_np import euler_to_matrix

# (overhang past the distal joint, distal/proximal radius) of the limb frustums. A frustum of
# taper t has its COM at (1 + 2t + 3t^2) / (4 (1 + t + t^2)) of its length: these put the COM
# within 0.05 of de Leva's position (thigh 0.39, shank 0.44, upper arm 0.58, forearm 0.46).
LIMB_SHAPE = {"thigh": (0.0, 0.55), "shank": (0.0, 0.70), "upper_arm": (0.12, 0.85), "forearm": (0.05, 0.67)}
# Starting radius (of stature) of each kind of shape; the mass match rescales it.
_START_RADIUS = {
    "thigh": 0.045,
    "shank": 0.03,
    "upper_arm": 0.025,
    "forearm": 0.02,
    "girdle": 0.03,
    "neck": 0.03,
    "finger": 0.006,
    "toe": 0.012,
    "face": 0.01,
    "detail": 0.01,
    "link": 0.015,
}
# Trunk cross-section (half-width, half-depth) of stature at levels along mid-hip -> neck base.
TRUNK_PROFILE = (
    (-0.08, 0.075, 0.055),
    (0.0, 0.092, 0.062),
    (0.45, 0.080, 0.058),
    (0.85, 0.098, 0.066),
    (1.0, 0.075, 0.050),
)
# Where a detail or girdle body's mass is budgeted.
_BUDGET = {"finger": "hand", "toe": "foot", "face": "head", "detail": "trunk"}
# A segment the rig lacks hands its mass to this one.
_FALLBACK = {
    "hand": "forearm",
    "forearm": "upper_arm",
    "upper_arm": "trunk",
    "foot": "shank",
    "shank": "thigh",
    "thigh": "trunk",
    "head": "trunk",
}


@dataclasses.dataclass(frozen=True)
class BodyPlan:
    """Which joints carry bodies, and each body's shape (body frame) and mass properties."""

    joint_body: tuple[int, ...]  # per joint: body index or -1
    body_joint: tuple[int, ...]
    shapes: tuple[poly.Polyhedron, ...]
    mass: np.ndarray  # (B,)
    com: np.ndarray  # (B, 3) body frame
    inertia: np.ndarray  # (B, 3, 3) about the COM, body frame
    body_segment: tuple[str, ...]  # budget segment of each body (trunk, head, thigh, ...)
    body_mass: float  # kg, the total
    segment_mass: dict  # (segment, side) -> kg


def world_frames(clip: BvhClip, offsets: np.ndarray, frame: int | None) -> tuple[np.ndarray, np.ndarray]:
    """World origins (J, 3) and rotations (J, 3, 3) of every joint at one frame of the clip,
    with the fixed ``offsets`` (non-root translation channels replaced as in the model); frame
    None is the zero pose (every rotation 0, the root at the origin).

    Not :func:`neuromotor.model.clip_edit.forward_kinematics`: that one follows the file's
    translation channels frame by frame (what the capture shows); the bodies are shaped on the
    model's fixed offsets."""
    n = len(clip.joints)
    pos, rot = np.zeros((n, 3)), np.zeros((n, 3, 3))
    row = None if frame is None else np.asarray(clip.motion[frame], dtype=np.float64)
    for k, joint in enumerate(clip.joints):
        cols = joint.rotation_columns
        local = (
            euler_to_matrix(np.deg2rad(row[list(cols)]), joint.rotation_order)
            if cols and row is not None
            else np.eye(3)
        )
        if joint.parent < 0:
            t = (
                np.zeros(3)
                if row is None
                else row[list(joint.translation_columns)]
                if joint.translation_columns
                else joint.offset
            )
            pos[k], rot[k] = t, local
        else:
            p = joint.parent
            pos[k] = pos[p] + rot[p] @ offsets[k]
            rot[k] = rot[p] @ local
    return pos, rot


def _unit(v, fallback=None):
    n = float(np.linalg.norm(v))
    if n > 1e-12:
        return np.asarray(v, np.float64) / n
    if fallback is None:
        raise ValueError("zero vector")
    return _unit(fallback)


def _perp(v, axis, fallback):
    """Unit part of ``v`` orthogonal to the unit ``axis`` (``fallback`` when ``v`` is parallel)."""
    w = np.asarray(v, np.float64) - np.dot(v, axis) * axis
    if np.linalg.norm(w) < 1e-6 * max(1.0, float(np.linalg.norm(v))):
        w = np.asarray(fallback, np.float64) - np.dot(fallback, axis) * axis
        if np.linalg.norm(w) < 1e-9:
            helper = np.zeros(3)
            helper[int(np.argmin(np.abs(axis)))] = 1.0
            w = helper - np.dot(helper, axis) * axis
    return _unit(w)


class _Geometry:
    """The clip in the pose the shapes are built on, in world coordinates, with its anatomy."""

    def __init__(self, clip: BvhClip, anatomy: Anatomy, offsets: np.ndarray):
        self.clip, self.anat = clip, anatomy
        self.seg = anatomy.segment
        self.n = len(clip.joints)
        self.children: list[list[int]] = [[] for _ in range(self.n)]
        for k, j in enumerate(clip.joints):
            if j.parent >= 0:
                self.children[j.parent].append(k)
        self.pos, self.rot = world_frames(clip, offsets, anatomy.shape_frame)
        self.H = float(anatomy.stature)
        up = anatomy.up if anatomy.shape_up is None else anatomy.shape_up
        forward = anatomy.forward if anatomy.shape_forward is None else anatomy.shape_forward
        self.up = _unit(up)
        self.forward = _perp(forward, self.up, np.roll(self.up, 1))
        self.left = np.cross(self.up, self.forward)

    def descendants(self, k) -> list[int]:
        out, stack = [], list(self.children[k])
        while stack:
            c = stack.pop()
            out.append(c)
            stack.extend(self.children[c])
        return out

    def end_point(self, k):
        """World position of joint k's End Site, or None."""
        e = self.clip.joints[k].end_site
        return None if e is None else self.pos[k] + self.rot[k] @ e

    def tip_points(self, k) -> np.ndarray:
        """World positions of everything below joint k: descendant joints and End Sites."""
        pts = []
        for j in [k] + self.descendants(k):
            if j != k:
                pts.append(self.pos[j])
            e = self.end_point(j)
            if e is not None:
                pts.append(e)
        return np.array(pts).reshape(-1, 3)

    def to_body(self, k, points):
        return (np.asarray(points) - self.pos[k]) @ self.rot[k]

    def dir_to_body(self, k, v):
        return np.asarray(v) @ self.rot[k]

    def parent_dir(self, k):
        p = self.clip.joints[k].parent
        if p < 0:
            return self.up
        return _unit(self.pos[k] - self.pos[p], self.up)


def _is_girdle(g: _Geometry, k: int) -> bool:
    """A trunk joint inside one limb's branch (clavicle, CMU's hip link): shaped as a limb."""
    below = [g.seg[j] for j in g.descendants(k)]
    limbs = below.count("upper_arm") + below.count("thigh")
    return limbs == 1 and "head" not in below and g.seg[k] == "trunk"


def _limb_rings(origin_b, tip_b, r, overhang, taper, sides):
    length = float(np.linalg.norm(tip_b - origin_b))
    axis = _unit(tip_b - origin_b)
    u = _perp(np.array([1.0, 0.0, 0.0]), axis, [0.0, 1.0, 0.0])
    v = np.cross(axis, u)
    end = origin_b + axis * length * (1.0 + overhang)
    return [poly.ellipse_ring(origin_b, u, v, r, r, sides), poly.ellipse_ring(end, u, v, r * taper, r * taper, sides)]


class _Shaper:
    """Builds each body's hull as a function of its segment's cross-section factor ``c``."""

    def __init__(self, g: _Geometry, is_body, sides: int):
        self.g, self.is_body, self.sides = g, is_body, sides
        H = g.H
        seg = g.seg
        thighs = [k for k in range(g.n) if seg[k] == "thigh" and seg[g.clip.joints[k].parent] != "thigh"]
        necks = [
            k
            for k in range(g.n)
            if seg[k] == "head" and (g.clip.joints[k].parent < 0 or seg[g.clip.joints[k].parent] != "head")
        ]
        self.trunk_ok = len(thighs) >= 1 and len(necks) >= 1
        if self.trunk_ok:
            self.midhip = g.pos[thighs].mean(0)
            self.neck = g.pos[necks[0]]
            span = self.neck - self.midhip
            self.trunk_len = max(float(np.linalg.norm(span)), 0.2 * H)
            self.axis = _unit(span, g.up)
            self.lat = _perp(g.left, self.axis, g.forward)
            self.fwd = np.cross(self.lat, self.axis)
            self.pelvis = min(
                (
                    k
                    for k in range(g.n)
                    if seg[k] == "trunk" and is_body[k] and all(t in g.descendants(k) for t in thighs)
                ),
                key=lambda k: -len(self._ancestors(k)),
                default=None,
            )

    def _ancestors(self, k):
        out = []
        while self.g.clip.joints[k].parent >= 0:
            k = self.g.clip.joints[k].parent
            out.append(k)
        return out

    def _trunk_ring(self, p, level, c):
        knots = np.array(TRUNK_PROFILE)
        w = np.interp(level, knots[:, 0], knots[:, 1]) * self.g.H * c
        d = np.interp(level, knots[:, 0], knots[:, 2]) * self.g.H * c
        return poly.ellipse_ring(p, self.lat, self.fwd, w, d, self.sides)

    def _level(self, p):
        return float(np.dot(p - self.midhip, self.axis)) / self.trunk_len

    def _trunk_points(self, k, c):
        g = self.g
        ends = [g.pos[c_] for c_ in g.children[k] if g.seg[c_] in ("trunk", "head") and not _is_girdle(g, c_)]
        pts = [g.pos[k]] + ends
        rings = []
        for p in pts:
            rings.append(self._trunk_ring(p, self._level(p), c))
        knots = [lv for lv, _, _ in TRUNK_PROFILE]
        for p in ends:  # profile knots inside a long bone
            l0, l1 = self._level(g.pos[k]), self._level(p)
            for lv in knots:
                if min(l0, l1) < lv < max(l0, l1):
                    s = (lv - l0) / (l1 - l0)
                    rings.append(self._trunk_ring(g.pos[k] + s * (p - g.pos[k]), lv, c))
        if k == self.pelvis:
            rings.append(self._trunk_ring(self.midhip, 0.0, c))
            low = self.midhip - 0.08 * self.trunk_len * self.axis
            rings.append(self._trunk_ring(low, -0.08, c))
        pts = np.concatenate(rings)
        along = (pts - g.pos[k]) @ self.axis
        if np.ptp(along) < 0.02 * self.g.H:  # a zero-length trunk link: a slab of the trunk
            lift = 0.01 * self.g.H * self.axis
            pts = np.concatenate([pts - lift, pts + lift])
        return g.to_body(k, pts)

    def _chain_tip(self, k):
        """World point a limb-like body of joint k reaches: its longest child bone or End Site."""
        g = self.g
        cands = [g.pos[c_] for c_ in g.children[k] if g.seg[c_] not in DETAIL_SEGMENTS or self.is_body[c_]]
        e = g.end_point(k)
        if e is not None:
            cands.append(e)
        if not cands:
            return None
        return max(cands, key=lambda p: float(np.linalg.norm(p - g.pos[k])))

    def points(self, k, c) -> np.ndarray:
        g, H, seg = self.g, self.g.H, self.g.seg[k]
        s = self.sides
        if seg == "trunk" and self.trunk_ok and not _is_girdle(g, k):
            return self._trunk_points(k, c)
        if seg == "hand":
            return self._hand(k, c)
        if seg == "foot":
            return self._foot(k, c)
        if seg == "head" and not any(g.seg[j] == "head" for j in g.children[k]):
            return self._skull(k, c)
        kind = "girdle" if seg == "trunk" else "neck" if seg == "head" else seg
        tip = self._chain_tip(k)
        r = _START_RADIUS.get(kind, 0.02) * H * c
        if tip is None or np.linalg.norm(tip - g.pos[k]) < 0.01 * H:
            r = _START_RADIUS["link"] * H * c  # zero-length link inside a chain
            return poly.box(np.full(3, r)).vertices
        overhang, taper = LIMB_SHAPE.get(seg, (0.0, 1.0))
        return np.concatenate(_limb_rings(np.zeros(3), g.to_body(k, tip), r, overhang, taper, s))

    def _hand(self, k, c):
        g, H = self.g, self.g.H
        tips = g.tip_points(k)
        d = None
        if len(tips):
            mean = tips.mean(0) - g.pos[k]
            if np.linalg.norm(mean) > 0.01 * H:
                d = _unit(mean)
        if d is None:
            d = g.parent_dir(k)
        across = tips - g.pos[k] if len(tips) >= 2 else np.zeros((0, 3))
        w = None
        if len(across) >= 2:  # spread of the finger points across the hand
            perp = across - np.outer(across @ d, d)
            _, sv, vt = np.linalg.svd(perp - perp.mean(0))
            if sv[0] > 0.01 * H:
                w = vt[0]
        w = _perp(g.forward if w is None else w, d, g.left)
        t = np.cross(d, w)
        length = deleva.LENGTH_OF_STATURE["hand_full"] * H
        if any(self.is_body[j] for j in g.children[k]):
            length *= 0.5  # fingers simulated as bodies of their own: the palm only
        stations = ((0.0, 0.022, 0.013), (0.4, 0.026, 0.012), (1.0, 0.018, 0.006))
        rings = [
            poly.ellipse_ring(g.pos[k] + f * length * d, w, t, a * H * c, b * H * c, self.sides) for f, a, b in stations
        ]
        return g.to_body(k, np.concatenate(rings))

    def _foot(self, k, c):
        g, H = self.g, self.g.H
        up = g.up
        tips = g.tip_points(k)
        f = None
        if len(tips):
            mean = tips.mean(0) - g.pos[k]
            horiz = mean - np.dot(mean, up) * up
            if np.linalg.norm(horiz) > 0.01 * H:
                f = _unit(horiz)
        if f is None:
            f = g.forward
        lat = np.cross(up, f)
        length = deleva.LENGTH_OF_STATURE["foot"] * H
        ah = deleva.LENGTH_OF_STATURE["ankle_height"] * H
        pts = []
        # (position along the foot, half-width, top above the sole) in stature fractions
        for s, hw, top in ((-0.22, 0.022, 0.8), (0.0, 0.025, 1.35), (0.55, 0.03, 0.55), (0.78, 0.018, 0.25)):
            for side in (-1.0, 1.0):
                for z in (0.0, top):
                    pts.append(g.pos[k] + s * length * f + side * hw * H * c * lat + (z * c - 1.0) * ah * up)
        return g.to_body(k, np.array(pts))

    def _skull(self, k, c):
        g, H = self.g, self.g.H
        e = g.end_point(k)
        d = g.parent_dir(k) if g.clip.joints[k].parent >= 0 else g.up
        length = None
        if e is not None and 0.06 * H <= np.linalg.norm(e - g.pos[k]) <= 0.22 * H:
            d, length = _unit(e - g.pos[k]), float(np.linalg.norm(e - g.pos[k]))
        if length is None:
            neck = 0.0
            j = k
            while g.clip.joints[j].parent >= 0 and g.seg[g.clip.joints[j].parent] == "head":
                neck += float(np.linalg.norm(g.pos[j] - g.pos[g.clip.joints[j].parent]))
                j = g.clip.joints[j].parent
            length = max(0.10 * H, deleva.LENGTH_OF_STATURE["head"] * H - neck)
        lat = _perp(g.left, d, g.forward)
        fwd = np.cross(lat, d)
        rings = []
        for s, hw, hd, ahead in (
            (-0.1, 0.030, 0.035, 0.0),
            (0.35, 0.044, 0.052, 0.012),
            (0.7, 0.042, 0.050, 0.012),
            (1.0, 0.020, 0.025, 0.006),
        ):
            centre = g.pos[k] + s * length * d + ahead * H * fwd
            rings.append(poly.ellipse_ring(centre, lat, fwd, hw * H * c, hd * H * c, self.sides))
        return g.to_body(k, np.concatenate(rings))


def _budget_segment(g: _Geometry, k: int) -> str:
    seg = g.seg[k]
    return _BUDGET.get(seg, seg)


def _is_body(clip: BvhClip, g: _Geometry, simulate_extremities: bool) -> list[bool]:
    """Which joints are bodies: an eligible joint (not extremity detail, unless simulated) with
    a bone of at least 1 % of the stature, a hand, a foot, the skull, or one with a body below."""
    n, H = g.n, g.H
    eligible = [g.seg[k] not in DETAIL_SEGMENTS or simulate_extremities for k in range(n)]
    always = ("hand", "foot")
    is_body = [False] * n
    for k in reversed(range(n)):  # children first: a joint with a body below it is a body
        if not eligible[k]:
            continue
        tip_len = 0.0
        for c_ in g.children[k]:
            if eligible[c_]:
                tip_len = max(tip_len, float(np.linalg.norm(g.pos[c_] - g.pos[k])))
        e = g.end_point(k)
        if e is not None:
            tip_len = max(tip_len, float(np.linalg.norm(e - g.pos[k])))
        skull = g.seg[k] == "head" and not any(g.seg[c_] == "head" for c_ in g.children[k])
        is_body[k] = tip_len >= 0.01 * H or g.seg[k] in always or skull or any(is_body[c_] for c_ in g.children[k])
    if not is_body[0]:
        raise UserError(f"{clip.path}: the root joint {clip.joints[0].name!r} carries no body")
    return is_body


def _mass_targets(groups: dict[tuple[str, str], list[int]], sex: str, total: float) -> dict:
    """Mass of each (budget segment, side) group: de Leva's fraction of ``total``, a segment the
    rig lacks carried by its parent segment, normalised to ``total``."""
    fractions = deleva.mass_fractions(sex)
    target: dict[tuple[str, str], float] = {}
    for seg, frac in fractions.items():
        for side in ("left", "right") if seg not in ("trunk", "head") else ("",):
            share = frac * total
            key = (seg, side)
            while key not in groups:  # the rig lacks this segment: its parent segment carries it
                parent = _FALLBACK.get(key[0])
                if parent is None:
                    break
                key = (parent, side if parent not in ("trunk", "head") else "")
            if key in groups:
                target[key] = target.get(key, 0.0) + share
    # Unpaired limb labels (no side found) fall back to an even share of both sides.
    for key in groups:
        if key not in target:
            seg, side = key
            target[key] = fractions.get(seg, 0.0) * total * (2.0 if seg not in ("trunk", "head") else 1.0)
    scale_total = total / sum(target.values())
    return {k: v * scale_total for k, v in target.items()}


def _fit_shapes(groups, target, shaper: _Shaper, density: float) -> tuple[dict, dict]:
    """Hulls and mass properties of every body, each group's shapes scaled in girth until the
    group weighs its target."""
    shape_of: dict[int, poly.Polyhedron] = {}
    props: dict[int, tuple] = {}
    for key, members in groups.items():
        c = 1.0
        for _ in range(40):
            hulls = {k: poly.convex_hull(shaper.points(k, c)) for k in members}
            got = {k: poly.mass_properties(h, density) for k, h in hulls.items()}
            m = sum(p[0] for p in got.values())
            ratio = target[key] / m
            if abs(ratio - 1.0) < 1e-10:
                break
            c *= ratio**0.5
        shape_of.update(hulls)
        props.update(got)
    return shape_of, props


def plan_bodies(
    clip: BvhClip,
    anatomy: Anatomy,
    offsets: np.ndarray,
    *,
    body_mass: float | None = None,
    sex: str = "average",
    density: float = 1000.0,
    simulate_extremities: bool = False,
    sides: int = 10,
) -> BodyPlan:
    """Bodies, shapes and mass properties of a clip whose joints ``anatomy`` has labelled."""
    g = _Geometry(clip, anatomy, offsets)
    n, H = g.n, g.H
    total = float(body_mass) if body_mass is not None else deleva.DEFAULT_BMI * H * H
    is_body = _is_body(clip, g, simulate_extremities)
    shaper = _Shaper(g, is_body, sides)
    body_joint = tuple(k for k in range(n) if is_body[k])
    groups: dict[tuple[str, str], list[int]] = {}
    for k in body_joint:
        seg = _budget_segment(g, k)
        side = anatomy.side[k] if seg not in ("trunk", "head") else ""
        groups.setdefault((seg, side), []).append(k)
    shape_of, props = _fit_shapes(groups, _mass_targets(groups, sex, total), shaper, density)

    masses = np.array([props[k][0] for k in body_joint])
    joint_body = [-1] * n
    for b, k in enumerate(body_joint):
        joint_body[k] = b
    seg_mass = {
        f"{s}{'_' + side if side else ''}": float(sum(props[k][0] for k in groups[(s, side)])) for (s, side) in groups
    }
    return BodyPlan(
        joint_body=tuple(joint_body),
        body_joint=body_joint,
        shapes=tuple(shape_of[k] for k in body_joint),
        mass=masses,
        com=np.stack([props[k][1] for k in body_joint]),
        inertia=np.stack([props[k][2] for k in body_joint]),
        body_segment=tuple(_budget_segment(g, k) for k in body_joint),
        body_mass=float(masses.sum()),
        segment_mass=seg_mass,
    )


# ---------------------------------------------------------------- skeletons that are not humanoid


@dataclasses.dataclass(frozen=True)
class GenericShapes:
    """Shape rule for skeletons the anatomy cannot read as a human (a pendulum, a test chain):
    each bone is wrapped by a prism, a body is the convex hull of its bones' prisms. Limb bones
    get radius ``limb_radius_ratio * L``; bodies with two or more leaves below them (a trunk)
    ``trunk_radius_ratio * span`` (span: the largest leaf-to-leaf path); every radius is at least
    ``min_radius``; a bone shorter than ``min_bone_length`` does not count, and a joint with no
    counted bone below it carries no body."""

    limb_radius_ratio: float = 0.15
    trunk_radius_ratio: float = 0.055
    min_radius: float = 0.02
    min_bone_length: float = 0.03
    sides: int = 8


def _leaf_counts(children, has_end):
    counts = [0] * len(children)
    for j in reversed(range(len(children))):
        counts[j] = int(has_end[j] or not children[j]) + sum(counts[c] for c in children[j])
    return counts


def _tree_span(clip: BvhClip, offsets, children) -> float:
    """Largest leaf-to-leaf path length along bones (the tree's weighted diameter)."""
    best, depth = 0.0, [0.0] * len(clip.joints)
    for j in reversed(range(len(clip.joints))):
        paths = [depth[c] + float(np.linalg.norm(offsets[c])) for c in children[j]]
        end_site = clip.joints[j].end_site
        if end_site is not None:
            paths.append(float(np.linalg.norm(end_site)))
        paths.sort(reverse=True)
        depth[j] = paths[0] if paths else 0.0
        if len(paths) >= 2:
            best = max(best, paths[0] + paths[1])
        best = max(best, depth[j])
    return best


def plan_generic(
    clip: BvhClip, offsets: np.ndarray, density: float = 1000.0, rule: GenericShapes = GenericShapes()
) -> BodyPlan:
    """Bodies of a non-humanoid skeleton by :class:`GenericShapes` at the given density."""
    joints, n = clip.joints, len(clip.joints)
    children: list[list[int]] = [[] for _ in range(n)]
    for k, j in enumerate(joints):
        if j.parent >= 0:
            children[j.parent].append(k)
    bones = [
        [offsets[c] for c in children[k]] + ([np.asarray(joints[k].end_site)] if joints[k].end_site is not None else [])
        for k in range(n)
    ]
    bone_len = [max((float(np.linalg.norm(e)) for e in bones[k]), default=0.0) for k in range(n)]
    has_body = [False] * n
    for k in reversed(range(n)):
        has_body[k] = bone_len[k] >= rule.min_bone_length or any(has_body[c] for c in children[k])
    if not has_body[0]:
        raise UserError(
            f"{clip.path}: the skeleton has no bone longer than {rule.min_bone_length} m; nothing to simulate"
        )
    leaves = _leaf_counts(children, [j.end_site is not None for j in joints])
    span = _tree_span(clip, offsets, children)
    body_joint = tuple(k for k in range(n) if has_body[k])
    shapes, props = [], []
    for k in body_joint:
        segs = []
        for end in bones[k]:
            length = float(np.linalg.norm(end))
            if length < rule.min_bone_length:
                continue
            r = rule.trunk_radius_ratio * span if leaves[k] >= 2 else rule.limb_radius_ratio * length
            segs.append((np.zeros(3), end, max(r, rule.min_radius)))
        shape = poly.segment_hull(segs, sides=rule.sides) if segs else poly.box(np.full(3, rule.min_radius))
        shapes.append(shape)
        props.append(poly.mass_properties(shape, density))
    joint_body = [-1] * n
    for b, k in enumerate(body_joint):
        joint_body[k] = b
    mass = np.array([p[0] for p in props])
    return BodyPlan(
        tuple(joint_body),
        body_joint,
        tuple(shapes),
        mass,
        np.stack([p[1] for p in props]),
        np.stack([p[2] for p in props]),
        tuple("trunk" for _ in body_joint),
        float(mass.sum()),
        {"trunk": float(mass.sum())},
    )
