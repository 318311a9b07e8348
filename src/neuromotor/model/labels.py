"""Which joint of a humanoid BVH skeleton from the wild is which (numpy only), in file units.

:func:`label_joints` labels every joint with the body segment it carries, its side and its mirror
joint, and finds the world up axis, the facing direction, a reference frame, the pose the body
shapes are built on and the body's height. It works from topology, bone lengths and the motion,
never from the rest pose's orientation and only as a last resort from names:

* Limbs are the two largest pairs of sibling subtrees with matching bone-length structure; the
  pair whose two longest consecutive bones are longer is the legs (thigh + shank is ~1.5x upper
  arm + forearm), else the pair branching nearer the root, else names.
* Along a limb's main chain (to its farthest leaf) the two consecutive longest "bones" are upper
  arm/forearm (thigh/shank). A bone may span several joints: a zero-length joint joins the bone
  after it, and a twist joint (its bones collinear in every frame while it turns) joins the bone
  before it. The joint that ends the second bone is the hand (foot); below it are fingers (toes).
* The head is the largest other branch at (or nearest above) the arms' branch joint; its chain
  climbs along the up axis, the rest under it is face.
* Up is the coordinate axis nearest to the mean of head top minus mid-ankles over the clip; the
  facing direction comes from the feet (ankle to toe), else the knees; left = up x forward.
* The height comes from the long bones with de Leva's (1996) segment/stature ratios.
* The body shapes are built on the zero pose when it stands (head above the feet along an axis,
  straight hanging legs, upright trunk), from the skeleton alone; else on the most upright frame.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np

from neuromotor.model.bvh import BvhClip
from neuromotor.model.clip_edit import forward_kinematics
from neuromotor.model.facing import horizontal
from neuromotor.rotations_np import rotation_angle

__all__ = ["SEGMENTS", "DETAIL_SEGMENTS", "JointLabels", "label_joints"]

SEGMENTS = (
    "trunk",
    "head",
    "upper_arm",
    "forearm",
    "hand",
    "thigh",
    "shank",
    "foot",
    "finger",
    "toe",
    "face",
    "detail",
)
DETAIL_SEGMENTS = frozenset({"finger", "toe", "face", "detail"})  # extremity detail, not simulated by default

# de Leva (1996) segment lengths relative to stature (sexes averaged).
_LEG_RATIO = 0.2425 + 0.2493  # thigh + shank
_ARM_RATIO = 0.1618 + 0.1545  # upper arm + forearm
_MAX_FK_FRAMES = 400  # analysis needs the motion's shape, not every frame
_MATCH_REL = 0.12  # solved skeletons differ left/right by ~1-3 %; 12 % leaves room
_TWIST_COLLINEAR_DEG = 3.0
_TWIST_TURN_DEG = 5.0


@dataclasses.dataclass(frozen=True)
class JointLabels:
    """What :func:`label_joints` finds (the fields of :class:`neuromotor.model.anatomy.Anatomy`
    that do not depend on the unit) and ``height``, the body's height in file units."""

    segment: tuple[str, ...]
    side: tuple[str, ...]
    mirror: tuple[int, ...]
    up: np.ndarray
    forward: np.ndarray
    reference_frame: int
    height: float
    warnings: tuple[str, ...]
    limb_chains: dict  # empty when no two limb pairs were found
    shape_frame: int | None = None
    shape_up: np.ndarray | None = None
    shape_forward: np.ndarray | None = None


# --------------------------------------------------------------------------------------------
# Skeleton structure


_LEFT_RE = re.compile(r"left|links|gauche|izquierd|sinistr", re.IGNORECASE)
_RIGHT_RE = re.compile(r"right|rechts|droit|derech|destr", re.IGNORECASE)


def _name_side(name: str) -> str:
    """'left'/'right' from a name, '' if it does not say."""
    if _LEFT_RE.search(name) and not _RIGHT_RE.search(name):
        return "left"
    if _RIGHT_RE.search(name) and not _LEFT_RE.search(name):
        return "right"
    for side, letter in (("left", "l"), ("right", "r")):
        # L_x, x_L, x.L, x-L, Lx (L then a capital: LHipJoint), xL at the end after lower case
        if re.search(rf"(^|[_.\-\s:|]){letter}([_.\-\s:|]|$)", name, re.IGNORECASE):
            return side
        if re.match(rf"^{letter.upper()}(?=[A-Z])", name) or re.search(rf"[a-z]{letter.upper()}$", name):
            return side
    return ""


_LEG_WORDS = re.compile(r"leg|thigh|knee|foot|feet|ankle|toe|hip|shin|calf", re.IGNORECASE)
_ARM_WORDS = re.compile(r"arm|shoulder|elbow|hand|wrist|clav|collar|finger|thumb", re.IGNORECASE)


class _Tree:
    """Topology and bone lengths of a clip (file units)."""

    def __init__(self, clip: BvhClip):
        J = len(clip.joints)
        self.J = J
        self.parents = [j.parent for j in clip.joints]
        self.children: list[list[int]] = [[] for _ in range(J)]
        for k, p in enumerate(self.parents):
            if p >= 0:
                self.children[p].append(k)
        offsets = np.zeros((J, 3))
        for k, joint in enumerate(clip.joints):
            cols = joint.translation_columns
            # Translation channels replace the OFFSET: their mean is the bone.
            offsets[k] = clip.motion[:, list(cols)].mean(axis=0) if cols else joint.offset
        self.offsets = offsets
        self.L = np.linalg.norm(offsets, axis=1)
        self.L[0] = 0.0
        self.end_len = np.array([0.0 if j.end_site is None else float(np.linalg.norm(j.end_site)) for j in clip.joints])
        self.reach = np.zeros(J)
        for k in range(J - 1, -1, -1):
            best = self.end_len[k]
            for c in self.children[k]:
                best = max(best, self.L[c] + self.reach[c])
            self.reach[k] = best
        self.size = max(
            float(self.reach[0] + max((self.L[c] + self.reach[c] for c in self.children[0]), default=0.0)), 1e-12
        )
        self.tiny = 1e-4 * self.size
        self.sub_end = [0] * J
        for k in range(J - 1, -1, -1):
            self.sub_end[k] = max([k + 1] + [self.sub_end[c] for c in self.children[k]])

    def subtree(self, k: int) -> range:
        return range(k, self.sub_end[k])

    def is_below(self, j: int, k: int) -> bool:
        return k <= j < self.sub_end[k]

    def path_to_root(self, k: int) -> list[int]:
        out = []
        while k >= 0:
            out.append(k)
            k = self.parents[k]
        return out

    def main_chain(self, k: int) -> list[int]:
        """k then, repeatedly, the child leading to the farthest leaf (stops where the End Site is
        farther than any child's subtree)."""
        chain = [k]
        while True:
            kids = self.children[chain[-1]]
            if not kids:
                return chain
            best = max(kids, key=lambda c: (self.L[c] + self.reach[c], -c))
            if self.end_len[chain[-1]] > self.L[best] + self.reach[best]:
                return chain
            chain.append(best)

    def close(self, x: float, y: float) -> bool:
        return abs(x - y) <= _MATCH_REL * max(x, y) + 0.01 * self.size

    def match(self, a: int, b: int) -> dict[int, int] | None:
        """Joint-to-joint map of subtree a onto subtree b if they have the same structure and
        matching lengths, else None."""
        if not (
            self.close(self.L[a], self.L[b])
            and self.close(self.end_len[a], self.end_len[b])
            and self.close(self.reach[a], self.reach[b])
        ):
            return None
        ka, kb = self.children[a], self.children[b]
        if len(ka) != len(kb):
            return None
        out = {a: b}
        in_order = [self.match(x, y) for x, y in zip(ka, kb)]
        if all(m is not None for m in in_order):
            for m in in_order:
                assert m is not None  # checked above
                out.update(m)
            return out
        # Children listed in another order: greedy by length difference.
        cost = sorted((abs(self.L[x] - self.L[y]) + abs(self.reach[x] - self.reach[y]), x, y) for x in ka for y in kb)
        used_a, used_b = set(), set()
        for _, x, y in cost:
            if x in used_a or y in used_b:
                continue
            m = self.match(x, y)
            if m is not None:
                used_a.add(x)
                used_b.add(y)
                out.update(m)
        return out if len(used_a) == len(ka) else None

    def sibling_pairs(self) -> list[tuple[float, int, int, dict[int, int]]]:
        """(size, a, b, map) of every pair of sibling subtrees that match, largest first."""
        out = []
        for kids in self.children:
            for x in range(len(kids)):
                for y in range(x + 1, len(kids)):
                    a, b = kids[x], kids[y]
                    score = min(self.L[a] + self.reach[a], self.L[b] + self.reach[b])
                    if score <= 100 * self.tiny:
                        continue
                    m = self.match(a, b)
                    if m is not None:
                        out.append((float(score), a, b, m))
        out.sort(key=lambda e: (-e[0], e[1]))
        return out


@dataclasses.dataclass
class _Limb:
    chain: list[int]
    groups: list[list[int]]  # consecutive chain joints forming one bone
    group_len: list[float]
    upper: int  # index into groups
    hand: int | None  # joint ending the second long bone, or None (the chain ends there)
    end_point: int  # joint whose position or End Site ends the lower bone (see end_is_site)
    end_is_site: bool

    @property
    def window(self) -> float:
        return self.group_len[self.upper] + self.group_len[self.upper + 1]

    @property
    def upper_len(self) -> float:
        return self.group_len[self.upper]

    @property
    def lower_len(self) -> float:
        return self.group_len[self.upper + 1]


def _limb(tree: _Tree, pos: np.ndarray, rot: np.ndarray, ends: np.ndarray, member: int) -> _Limb:
    chain = tree.main_chain(member)
    n = len(chain)
    body = [tree.L[chain[i + 1]] if i + 1 < n else tree.end_len[chain[i]] for i in range(n)]

    def tip(i: int) -> np.ndarray:  # (T, 3) far end of chain[i]'s bone
        return pos[:, chain[i + 1]] if i + 1 < n else ends[:, chain[i]]

    groups: list[list[int]] = []
    pending: list[int] = []  # zero-length joints waiting for the next bone
    last_real = None  # chain index of the previous joint with a bone
    for i in range(n):
        if body[i] <= tree.tiny:
            pending.append(i)
            continue
        twist = False
        if last_real is not None:
            v1 = pos[:, chain[i]] - pos[:, chain[last_real]]
            v2 = tip(i) - pos[:, chain[i]]
            cos = np.sum(v1 * v2, axis=1) / np.maximum(np.linalg.norm(v1, axis=1) * np.linalg.norm(v2, axis=1), 1e-300)
            collinear = np.all(cos > math.cos(math.radians(_TWIST_COLLINEAR_DEG)))
            if collinear:
                rel = np.swapaxes(rot[:, chain[last_real]], 1, 2) @ rot[:, chain[i]]
                turn = rotation_angle(rel @ np.swapaxes(rel[:1], 1, 2))
                twist = bool(turn.max() > math.radians(_TWIST_TURN_DEG))
        if twist:
            groups[-1].extend(pending + [i])
        else:
            groups.append(pending + [i])
        pending = []
        last_real = i
    if pending:
        groups.append(pending)
    group_len = [float(sum(body[i] for i in g)) for g in groups]
    groups = [[chain[i] for i in g] for g in groups]
    if len(groups) < 2:
        groups.append([])
        group_len.append(0.0)
    limb = _Limb(chain, groups, group_len, 0, None, chain[0], True)
    _set_window(limb, max(range(len(groups) - 1), key=lambda g: (group_len[g] + group_len[g + 1], -g)))
    return limb


def _set_window(limb: _Limb, upper: int) -> None:
    groups = limb.groups
    limb.upper = upper
    limb.hand = groups[upper + 2][0] if upper + 2 < len(groups) and groups[upper + 2] else None
    lower_group = groups[upper + 1]
    if limb.hand is not None:
        limb.end_point, limb.end_is_site = limb.hand, False
    elif lower_group:
        limb.end_point, limb.end_is_site = lower_group[-1], True
    else:
        limb.end_point, limb.end_is_site = groups[upper][-1], True


def _choose_windows(a: _Limb, b: _Limb, mapping: dict[int, int], pos: np.ndarray) -> None:
    """Pick the two long bones of a pair of limbs together. Among windows within 10 % of the longest,
    the one starting farthest from its mirror joint: a clavicle or hip link starts near the midline,
    the upper arm or thigh well beside it (CMU's clavicle is longer than its forearm)."""
    if len(a.groups) != len(b.groups):
        return  # sides disagree on the bone split: keep each side's longest window
    n = len(a.groups) - 1
    sums = [0.5 * (a.group_len[g] + a.group_len[g + 1] + b.group_len[g] + b.group_len[g + 1]) for g in range(n)]
    best = max(sums)
    candidates = [g for g in range(n) if sums[g] >= 0.9 * best and a.groups[g] and a.groups[g][0] in mapping]
    if len(candidates) < 2:
        return

    def spread(g: int) -> float:
        j = a.groups[g][0]
        return float(np.linalg.norm(pos[:, j] - pos[:, mapping[j]], axis=1).mean())

    upper = max(candidates, key=lambda g: (spread(g), sums[g], -g))
    _set_window(a, upper)
    _set_window(b, upper)


def _nearest_axis(v: np.ndarray) -> np.ndarray:
    k = int(np.argmax(np.abs(v)))
    out = np.zeros(3)
    out[k] = 1.0 if v[k] >= 0 else -1.0
    return out


def _frame_rows(n_frames: int) -> np.ndarray:
    return np.unique(np.linspace(0, n_frames - 1, min(n_frames, _MAX_FK_FRAMES)).round().astype(int))


def _limb_pairs(tree: _Tree, pairs) -> list:
    """The first two sibling pairs (best matched first) that are disjoint: the limbs."""
    limbs_pairs: list = []
    for entry in pairs:
        _, a, b, _ = entry
        if any(
            a == x or b == x or tree.is_below(a, x) or tree.is_below(b, x) or tree.is_below(x, a) or tree.is_below(x, b)
            for e in limbs_pairs
            for x in (e[1], e[2])
        ):
            continue
        limbs_pairs.append(entry)
        if len(limbs_pairs) == 2:
            break
    return limbs_pairs


def _upward_children(tree: _Tree, pos, ends, cur: int, paired: set, up0) -> list[int]:
    """Children of head joint ``cur`` that continue the head chain upwards."""
    kids = [c for c in tree.children[cur] if c not in paired]
    upward = []
    lone = len(tree.children[cur]) == 1
    for c in kids:
        last = tree.main_chain(c)[-1]
        v = ends[:, last] - pos[:, cur]  # to the far end of c's branch
        length = np.linalg.norm(v, axis=1)
        if float(length.mean()) <= tree.tiny:
            rise = 1.0 if lone else -1.0
        else:
            rise = float(np.mean(v @ up0 / np.maximum(length, 1e-300)))
        # A lone child continues the chain unless its branch hangs down (a jaw); among
        # several, only a branch climbing steeply (the skull top, not a jaw).
        if rise > (-0.1 if lone else 0.5):
            upward.append(c)
    return upward


def _head_chain(tree: _Tree, pos, ends, arm_branch: int, limb_members: set, pairs, up0) -> list[int]:
    """Head joints from the neck up: the largest other branch at the arms' branch joint (else
    nearest above it), followed upwards; empty when there is none."""
    head0 = None
    for anc in tree.path_to_root(arm_branch):
        cands = [
            c
            for c in tree.children[anc]
            if c not in limb_members and not any(tree.is_below(m, c) for m in limb_members)
        ]
        if cands:
            head0 = max(cands, key=lambda c: (tree.L[c] + tree.reach[c], -c))
            break
    if head0 is None:
        return []
    paired: set[int] = set()
    for _, a, b, _ in pairs:
        paired.update((a, b))
    head_chain = [head0]
    while True:
        upward = _upward_children(tree, pos, ends, head_chain[-1], paired, up0)
        if not upward:
            return head_chain
        head_chain.append(max(upward, key=lambda c: (tree.L[c] + tree.reach[c], -c)))


def _facing_per_frame(tree: _Tree, pos, ends, legs, up, n_rows: int):
    """Facing per frame, unnormalised, from the feet (ankle to toe), else the knees; and which
    ("feet", "knees" or "" when neither tells)."""
    leg_len = float(np.mean([l.window for l in legs]))
    fwd_t = np.zeros((n_rows, 3))
    for l in legs:
        if l.hand is not None:
            foot_chain = tree.main_chain(l.hand)
            last = foot_chain[-1]
            toe = ends[:, last] if tree.end_len[last] > tree.tiny else pos[:, last]
            if np.linalg.norm(toe - pos[:, l.hand], axis=1).mean() > 0.05 * leg_len:
                fwd_t += horizontal(toe - pos[:, l.hand], up)
    if not np.linalg.norm(fwd_t, axis=1).mean() < 0.02 * leg_len:
        return fwd_t, "feet"
    fwd_t = np.zeros((n_rows, 3))
    for l in legs:
        hip = pos[:, l.groups[l.upper][0]]
        knee = pos[:, l.groups[l.upper + 1][0]] if l.groups[l.upper + 1] else hip
        ank = ends[:, l.end_point] if l.end_is_site else pos[:, l.end_point]
        fwd_t += horizontal(knee - 0.5 * (hip + ank), up)
    return fwd_t, ("" if np.linalg.norm(fwd_t, axis=1).mean() < 0.01 * leg_len else "knees")


@dataclasses.dataclass
class _Labels:
    """The per-joint labels and limb chains while :func:`analyse` fills them in."""

    segment: list[str]
    side: list[str]
    mirror: list[int]
    chains: dict = dataclasses.field(default_factory=dict)

    def apply_pair(self, mapping: dict[int, int], sides) -> None:
        for x, y in mapping.items():
            self.mirror[x], self.mirror[y] = y, x
            if sides is not None:
                self.side[x], self.side[y] = sides


@dataclasses.dataclass
class _SideJudge:
    """Tells left from right for two sibling branches: from the geometry (the facing direction
    per frame ``left_t``) when it tells, else from the joint names."""

    tree: _Tree
    pos: np.ndarray
    left_t: np.ndarray
    facing_from: str
    names: list[str]

    def mean_points(self, k: int) -> np.ndarray:
        sub = list(self.tree.subtree(k))
        return self.pos[:, sub].mean(axis=1)

    def decide(self, a: int, b: int) -> tuple[str, str] | None:
        """Sides of siblings a and b, from geometry, else names."""
        if self.facing_from:
            d = self.mean_points(a) - self.mean_points(b)
            lat = float(np.sum(d * self.left_t))
            norm = float(np.sum(np.linalg.norm(d, axis=1) * np.linalg.norm(self.left_t, axis=1)))
            if norm > 0 and abs(lat) > 0.2 * norm:
                return ("left", "right") if lat > 0 else ("right", "left")
        na, nb = _name_side(self.names[a]), _name_side(self.names[b])
        if {na, nb} == {"left", "right"}:
            return na, nb
        return None


def _label_limbs(
    labels: _Labels, judge: _SideJudge, tree: _Tree, pos_ref, ends_ref, limb_sets, warnings: list[str]
) -> None:
    """Sides, mirrors, segments and chains of the legs and arms."""
    names = judge.names
    for kind, pair, limb_pair in limb_sets:
        _, a, b, mapping = pair
        sides = judge.decide(a, b)
        if sides is None:
            warnings.append(
                f"cannot tell the left {kind} from the right one ({names[a]!r}, {names[b]!r}): "
                f"{names[a]!r} is taken as left"
            )
            sides = ("left", "right")
            labels.apply_pair(mapping, None)
            for x, y in mapping.items():
                labels.side[x], labels.side[y] = sides
        else:
            labels.apply_pair(mapping, sides)
        for limb, s in ((limb_pair[0], sides[0]), (limb_pair[1], sides[1])):
            _label_limb(tree, pos_ref, ends_ref, limb, kind, labels.segment)
            end = limb.hand if limb.hand is not None else (limb.groups[limb.upper + 1] or limb.groups[limb.upper])[-1]
            labels.chains[f"{kind}_{s}"] = tuple(limb.chain[: limb.chain.index(end) + 1])


def _label_other_pairs(labels: _Labels, judge: _SideJudge, tree: _Tree, pairs, limb_roots) -> None:
    """Other symmetric pairs outside the limbs (eyes, ...)."""
    for _, a, b, mapping in pairs:
        if (
            labels.mirror[a] >= 0
            or labels.mirror[b] >= 0
            or any(tree.is_below(a, m) or tree.is_below(b, m) for m in limb_roots)
        ):
            continue
        sides = judge.decide(a, b)
        if sides is not None:
            labels.apply_pair(mapping, sides)


def _label_head_and_trunk(labels: _Labels, tree: _Tree, head_chain, limb_roots, arm_branch) -> None:
    """Head chain and face; the trunk is every ancestor of a limb or of the head."""
    segment = labels.segment
    for k in head_chain:
        segment[k] = "head"
    for n_chain, k in enumerate(head_chain):
        for c in tree.children[k]:
            if c in head_chain:
                continue
            label = "detail" if (n_chain == 0 and len(head_chain) > 1) else "face"
            for j in tree.subtree(c):
                segment[j] = label
    if head_chain:
        labels.chains["head"] = tuple(head_chain)
    anchors = limb_roots + head_chain[:1]
    for m in anchors:
        for k in tree.path_to_root(tree.parents[m]):
            segment[k] = "trunk"
    segment[0] = "trunk"
    labels.chains["spine"] = tuple(reversed(tree.path_to_root(arm_branch)))


def _forward_at(ref_i: int, fwd_t, up, tree: _Tree, judge: _SideJudge, chains, warnings: list[str]) -> np.ndarray:
    """Unit horizontal facing at the reference frame (else over all frames, else from the legs'
    sides, else an arbitrary horizontal axis with a warning)."""
    f = fwd_t[ref_i]
    if np.linalg.norm(f) < 1e-9 * tree.size:
        f = fwd_t.sum(axis=0)
    if np.linalg.norm(f) < 1e-9 * tree.size:  # no geometric facing: from the legs' sides
        li = chains["leg_left"][0]
        ri = chains["leg_right"][0]
        lat = horizontal(judge.mean_points(li) - judge.mean_points(ri), up)[ref_i]
        f = np.cross(lat, up)
        if np.linalg.norm(f) < 1e-12:
            f = np.cross(up, np.roll(up, 1))
            warnings.append("facing direction unknown: an arbitrary horizontal axis is used")
    forward = horizontal(f[None], up)[0]
    return forward / np.linalg.norm(forward)


def _ankle_points(legs, pos, ends):  # (T, 2, 3)
    return np.stack([ends[:, l.end_point] if l.end_is_site else pos[:, l.end_point] for l in legs], axis=1)


_STANDING_COS = math.cos(math.radians(20.0))
_LEG_HANG_COS = math.cos(math.radians(30.0))  # CMU's zero pose stands with its feet 20 deg apart


def _zero_pose(tree: _Tree, clip: BvhClip) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions and End Site points (1, J, 3) of the zero pose (every rotation 0, the root at
    the origin, the tree's fixed offsets): the skeleton alone, no frame of the motion."""
    pos = np.zeros((1, tree.J, 3))
    for k in range(1, tree.J):
        pos[0, k] = pos[0, tree.parents[k]] + tree.offsets[k]
    ends = pos.copy()
    for k, joint in enumerate(clip.joints):
        if joint.end_site is not None:
            ends[0, k] = pos[0, k] + np.asarray(joint.end_site, dtype=np.float64)
    return pos, ends


def _standing_up(pos, ends, legs, head_chain, arm_branch) -> np.ndarray | None:
    """Up of a pose (1, J, 3) if it is a standing pose, else None: the head top above the
    mid-ankles along a coordinate axis and the trunk upright (within 20 deg), each leg straight
    and hanging (within 30 deg). Many rigs' zero pose is one; others keep the rest orientation
    in the motion (every bone along its joint's X axis) and stand only in their frames."""
    if not head_chain or any(not l.groups[l.upper] for l in legs):
        return None
    ankles = _ankle_points(legs, pos, ends)[0]
    v = ends[0, head_chain[-1]] - ankles.mean(axis=0)
    up = _nearest_axis(v)
    if not v @ up > _STANDING_COS * np.linalg.norm(v):
        return None
    hips = []
    for l, ankle in zip(legs, ankles):
        hip = pos[0, l.groups[l.upper][0]]
        d = ankle - hip
        if not (-d @ up > _LEG_HANG_COS * np.linalg.norm(d) and np.linalg.norm(d) > 0.9 * l.window):
            return None
        hips.append(hip)
    t = pos[0, arm_branch] - np.mean(hips, axis=0)
    return up if t @ up > _STANDING_COS * np.linalg.norm(t) else None


def _standing_forward(tree: _Tree, pos, ends, legs, up, chains) -> np.ndarray | None:
    """Unit facing of a standing pose (1, J, 3): from the feet, else left = up x forward from the
    labelled hips; None if neither tells."""
    f, facing_from = _facing_per_frame(tree, pos, ends, legs, up, 1)
    f = f[0]
    if not facing_from:
        lat = horizontal(pos[:, chains["leg_left"][0]] - pos[:, chains["leg_right"][0]], up)[0]
        f = np.cross(lat, up)
    f = horizontal(f[None], up)[0]
    n = float(np.linalg.norm(f))
    return f / n if n > 1e-9 * tree.size else None


def label_joints(clip: BvhClip) -> JointLabels:
    """Labels, up, facing, reference frame, shape pose and height of ``clip`` (lengths in file
    units). A skeleton without two limb pairs (not a person) gets every joint "trunk", up +y,
    forward +z, no limb chains and its height along y."""
    tree = _Tree(clip)
    rows = _frame_rows(clip.n_frames)
    pos, rot, ends = forward_kinematics(clip, rows)
    warnings: list[str] = []
    names = [j.name for j in clip.joints]
    pairs = tree.sibling_pairs()
    limbs_pairs = _limb_pairs(tree, pairs)
    if len(limbs_pairs) < 2:
        return _no_limbs(clip, pos, rows, warnings)

    limbs = [[_limb(tree, pos, rot, ends, e[1]), _limb(tree, pos, rot, ends, e[2])] for e in limbs_pairs]
    for (x, y), e in zip(limbs, limbs_pairs):
        _choose_windows(x, y, e[3], pos)
    legs_i = _pick_legs(tree, limbs_pairs, [0.5 * (x.window + y.window) for x, y in limbs], names)
    legs_pair, arms_pair = limbs_pairs[legs_i], limbs_pairs[1 - legs_i]
    legs, arms = limbs[legs_i], limbs[1 - legs_i]

    ankles = _ankle_points(legs, pos, ends).mean(axis=1)
    arm_branch = tree.parents[arms_pair[1]]
    up0 = _nearest_axis((pos[:, arm_branch] - ankles).mean(axis=0))
    limb_roots = [legs_pair[1], legs_pair[2], arms_pair[1], arms_pair[2]]
    head_chain = _head_chain(tree, pos, ends, arm_branch, set(limb_roots), pairs, up0)
    if head_chain:
        head_top = ends[:, head_chain[-1]]
    else:
        warnings.append("no head branch found: up is taken from the arms' branch joint")
        head_top = pos[:, arm_branch]
    up = _nearest_axis((head_top - ankles).mean(axis=0))
    ref_i = int(np.argmax((head_top - ankles) @ up))
    # Shapes are built on the zero pose when it stands (the skeleton alone, so a window or a
    # re-export of the clip gets the same body), else on the most upright of all frames (not
    # of the analysis sample, whose spacing depends on the clip's length).
    shape_pos, shape_ends = _zero_pose(tree, clip)
    shape_up = _standing_up(shape_pos, shape_ends, legs, head_chain, arm_branch)
    shape_frame = None
    if shape_up is None:
        shape_up = up
        all_pos, _, all_ends = forward_kinematics(clip)
        top = all_ends[:, head_chain[-1]] if head_chain else all_pos[:, arm_branch]
        shape_frame = int(np.argmax((top - _ankle_points(legs, all_pos, all_ends).mean(axis=1)) @ up))
        shape_pos, shape_ends = all_pos[shape_frame : shape_frame + 1], all_ends[shape_frame : shape_frame + 1]

    fwd_t, facing_from = _facing_per_frame(tree, pos, ends, legs, up, len(rows))
    judge = _SideJudge(tree, pos, np.cross(up, fwd_t), facing_from, names)
    labels = _Labels(["detail"] * tree.J, [""] * tree.J, [-1] * tree.J)
    _label_limbs(
        labels, judge, tree, shape_pos[0], shape_ends[0], (("leg", legs_pair, legs), ("arm", arms_pair, arms)), warnings
    )
    _label_other_pairs(labels, judge, tree, pairs, limb_roots)
    _label_head_and_trunk(labels, tree, head_chain, limb_roots, arm_branch)
    forward = _forward_at(ref_i, fwd_t, up, tree, judge, labels.chains, warnings)
    shape_forward = _standing_forward(tree, shape_pos, shape_ends, legs, shape_up, labels.chains)
    if shape_forward is None:
        shape_forward = forward if shape_frame is not None else horizontal(np.roll(shape_up, 1)[None], shape_up)[0]

    # Height from the long bones, sides averaged.
    leg = float(np.mean([l.window for l in legs]))
    arm = float(np.mean([l.window for l in arms]))
    height = (leg + arm) / (_LEG_RATIO + _ARM_RATIO) if arm > 0 else leg / _LEG_RATIO
    for v in (up, forward, shape_up, shape_forward):
        v.setflags(write=False)
    return JointLabels(
        tuple(labels.segment),
        tuple(labels.side),
        tuple(labels.mirror),
        up,
        forward,
        int(rows[ref_i]),
        height,
        tuple(warnings),
        labels.chains,
        shape_frame,
        shape_up,
        shape_forward,
    )


def _no_limbs(clip: BvhClip, pos, rows, warnings: list[str]) -> JointLabels:
    """Every joint trunk, up +y, forward +z: a skeleton without two limb pairs (not a person)."""
    J = len(clip.joints)
    warnings.append("no two symmetric limb pairs found: every joint is labelled trunk")
    up = np.array([0.0, 1.0, 0.0])
    extent = pos[:, :, 1].max(1) - pos[:, :, 1].min(1)
    ref = int(rows[int(np.argmax(extent))])
    height = float(extent.max()) or 1.0
    return JointLabels(
        ("trunk",) * J, ("",) * J, (-1,) * J, up, np.array([0.0, 0.0, 1.0]), ref, height, tuple(warnings), {}
    )  # generic shapes: the offsets alone


def _pick_legs(tree: _Tree, pairs, windows, names) -> int:
    """Index (0/1) of the legs among the two limb pairs."""
    big = int(windows[1] > windows[0])
    if max(windows) > 1.2 * min(windows):
        return big
    branch = [tree.parents[p[1]] for p in pairs]
    if branch[0] != branch[1]:
        if tree.is_below(branch[1], branch[0]):
            return 0
        if tree.is_below(branch[0], branch[1]):
            return 1
    votes = []
    for p in pairs:
        text = " ".join(names[j] for j in list(tree.subtree(p[1])) + list(tree.subtree(p[2])))
        votes.append(len(_LEG_WORDS.findall(text)) - len(_ARM_WORDS.findall(text)))
    if votes[0] != votes[1]:
        return int(votes[1] > votes[0])
    return big


def _label_limb(tree: _Tree, pos: np.ndarray, ends: np.ndarray, limb: _Limb, kind: str, segment: list[str]) -> None:
    """Labels of one limb's subtree (pos, ends: one frame)."""
    upper_name, lower_name, end_name, below_name = (
        ("thigh", "shank", "foot", "toe") if kind == "leg" else ("upper_arm", "forearm", "hand", "finger")
    )
    member = limb.chain[0]
    for k in tree.subtree(member):
        segment[k] = "detail"
    upper_group = limb.groups[limb.upper]
    lower_group = limb.groups[limb.upper + 1]
    for k in upper_group:
        segment[k] = upper_name
    for k in lower_group:
        segment[k] = lower_name
    first_bone = limb.chain.index(upper_group[0]) if upper_group else 0
    for k in limb.chain[:first_bone]:
        segment[k] = "trunk"
    if limb.hand is not None:
        for k in tree.subtree(limb.hand):
            segment[k] = below_name
        segment[limb.hand] = end_name
    # Branches off the long bones: part of the bone if they lie along it (a twist leaf), else detail.
    for group, name in ((upper_group, upper_name), (lower_group, lower_name)):
        if not group:
            continue
        a = pos[group[0]]
        last = group[-1]
        i = limb.chain.index(last)
        b = pos[limb.chain[i + 1]] if i + 1 < len(limb.chain) else ends[last]
        seg = b - a
        length = float(np.linalg.norm(seg))
        for k in group:
            for c in tree.children[k]:
                if c in limb.chain:
                    continue
                pts = np.concatenate([pos[list(tree.subtree(c))], ends[list(tree.subtree(c))]])
                if length > 0:
                    s = np.clip((pts - a) @ seg / length**2, 0.0, 1.0)
                    dist = np.linalg.norm(pts - (a + s[:, None] * seg), axis=1)
                    along = bool(dist.max() <= 0.1 * length)
                else:
                    along = False
                for j in tree.subtree(c):
                    segment[j] = name if along else "detail"
