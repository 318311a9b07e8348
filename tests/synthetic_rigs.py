"""Random humanoid BVH rigs with known anatomy, for tests of neuromotor.model.anatomy.

:func:`make_rig` builds a walking humanoid in a canonical world (Y up, facing +Z, left = +X), then
writes it as BVH text with the variations found in the wild: random (non-English) names, fingers,
toes, face and eyes, props on the trunk, twist joints, a CMU-style hip link, any Euler orders,
6 channels on every joint, zero-length End Sites, a zero pose that is not standing (every OFFSET
along the joint's own X axis, the rest orientation moved into the motion), Y or Z up with a random
heading, a ground-marker virtual root, and any length unit. Rotations use scipy, independently of
the code under test.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from scipy.spatial.transform import Rotation

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "cmu": 0.0254 / 0.45}
ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
_ALPHABET = "абвгдежзиклмнопстуфхцчшщэюяαβγδεζηθκμνξπστφχψω0123456789"


@dataclasses.dataclass
class Rig:
    text: str  # the BVH file
    names: list[str]  # body joints (without a virtual root), file order
    segment: list[str]  # true labels of the body joints
    side: list[str]
    mirror: list[int]  # indices into the body joints, -1 for none
    up: np.ndarray  # (3,) signed axis
    stature: float  # metres
    unit: str
    virtual_root: str | None  # name of the ground-marker ROOT, if any
    options: dict


@dataclasses.dataclass
class _Node:
    name: str
    parent: int
    pos: np.ndarray  # canonical world rest position, metres
    segment: str
    side: str
    role: str  # same role on both sides -> mirror pair
    rot: object  # phase (T,) -> local rotation matrices (T, 3, 3) in the canonical rest frame
    end: np.ndarray | None = None  # End Site vector, canonical world


def _rot(axis: str, deg) -> np.ndarray:
    deg = np.atleast_1d(np.asarray(deg, dtype=float))
    return Rotation.from_euler(axis, deg[:, None], degrees=True).as_matrix()


def _still(phase):
    return np.broadcast_to(np.eye(3), (len(phase), 3, 3)).copy()


def _names(rng, n: int) -> list[str]:
    out: set[str] = set()
    while len(out) < n:
        out.add("".join(rng.choice(list(_ALPHABET), size=int(rng.integers(3, 9)))))
    names = sorted(out)
    rng.shuffle(names)
    return names


def _orthonormal_with_x(d: np.ndarray, rng) -> np.ndarray:
    """A rotation whose first column is the unit vector d, random roll about it."""
    d = d / np.linalg.norm(d)
    a = rng.normal(size=3)
    a -= d * (a @ d)
    a /= np.linalg.norm(a)
    return np.stack([d, a, np.cross(d, a)], axis=1)


def make_rig(seed: int, **options) -> Rig:
    """A random rig; any option not given is drawn. Options: fingers, toes, face, props (0-2),
    twist, hip_link, six_channels, zero_end_sites, bent_zero_pose, up ("Y"/"Z"), virtual_root,
    unit (key of UNITS), stature (m), scale (extra factor, e.g. 2 for a giant), frames; thumbs and
    hand_end (a one-link thumb, a still tip joint under each hand without fingers; never drawn)."""
    rng = np.random.default_rng(seed)
    draw = {
        "fingers": bool(rng.random() < 0.5), "toes": bool(rng.random() < 0.6), "face": bool(rng.random() < 0.5),
        "props": int(rng.integers(0, 3)), "twist": bool(rng.random() < 0.4), "hip_link": bool(rng.random() < 0.3),
        "six_channels": bool(rng.random() < 0.3), "zero_end_sites": bool(rng.random() < 0.4),
        "bent_zero_pose": bool(rng.random() < 0.4), "up": str(rng.choice(["Y", "Z"])),
        "virtual_root": bool(rng.random() < 0.3), "unit": str(rng.choice(list(UNITS))),
        "stature": float(rng.uniform(1.5, 1.95)), "scale": 1.0, "frames": 60,
        "thumbs": False, "hand_end": False,  # not drawn: seeds keep their rigs
    }
    unknown = set(options) - set(draw)
    if unknown:
        raise TypeError(f"unknown options {sorted(unknown)}")
    draw.update(options)
    o = draw
    H = o["stature"]

    def jit(x: float) -> float:  # proportions vary between people
        return x * rng.uniform(0.95, 1.05)

    nodes: list[_Node] = []

    def add(parent, pos, segment, side="", role="", rot=_still, end=None) -> int:
        nodes.append(_Node("", parent, np.asarray(pos, dtype=float), segment, side, role, rot,
                           None if end is None else np.asarray(end, dtype=float)))
        return len(nodes) - 1

    period = rng.uniform(30, 50)
    speed = 1.2 * H / 1.75

    def swing(axis, amp, offset=0.0, lag=0.0, sign=1.0):
        return lambda ph: _rot(axis, offset + sign * amp * np.sin(ph + lag))

    # Pelvis and spine.
    pelvis_h = 0.53 * H
    root = add(-1, [0, pelvis_h, 0], "trunk", rot=lambda ph: _rot("y", 6 * np.sin(ph)))
    prop_slots = [root]
    zero = o["zero_end_sites"]

    def leg(s: float, side: str) -> None:
        asym = rng.uniform(0.98, 1.02)
        parent = root
        base = nodes[root].pos
        if o["hip_link"]:  # CMU: a zero-length joint whose bone goes to the hip joint
            parent = add(root, base, "trunk", side, "hiplink", rot=swing("z", 2))
        hip = base + [s * jit(0.05) * H, -0.04 * H, 0]
        hip_j = add(parent, hip, "thigh", side, "thigh", rot=lambda ph: _rot("x", -25 * s * np.sin(ph)) @ _rot("z", s * 3 + 0 * ph))
        knee = hip + [0, -jit(0.2425) * H * asym, 0.005 * H]
        knee_j = add(hip_j, knee, "shank", side, "shank", rot=lambda ph: _rot("x", 30 + 25 * np.sin(ph + (0 if s > 0 else np.pi) + 0.5)))
        ankle = knee + [0, -jit(0.2493) * H * asym, -0.005 * H]
        foot_vec = np.array([0, -0.035 * H, jit(0.11) * H])
        ankle_rot = lambda ph: _rot("x", 10 * np.sin(ph + (0 if s > 0 else np.pi)))
        if o["toes"]:
            foot_j = add(knee_j, ankle, "foot", side, "foot", rot=ankle_rot)
            add(foot_j, ankle + foot_vec, "toe", side, "toe", rot=lambda ph: _rot("x", 8 * np.sin(ph)),
                end=[0, 0, 0] if zero else [0, 0, jit(0.04) * H])
        else:
            add(knee_j, ankle, "foot", side, "foot", rot=ankle_rot, end=foot_vec)

    def arm(chest: int, s: float, side: str) -> None:
        asym = rng.uniform(0.98, 1.02)
        c = nodes[chest].pos
        clav_pos = c + [s * 0.02 * H, 0.04 * H, 0]
        clav = add(chest, clav_pos, "trunk", side, "clavicle", rot=swing("z", 3, sign=s))
        shoulder = clav_pos + [s * jit(0.09) * H, 0.005 * H, -0.01 * H]
        down = np.array([s * 0.05, -1.0, 0.0])
        down /= np.linalg.norm(down)
        upper = jit(0.1618) * H * asym
        fore = jit(0.1545) * H * asym
        lag = np.pi if s > 0 else 0.0
        ua = add(clav, shoulder, "upper_arm", side, "upper_arm",
                 rot=lambda ph: _rot("x", 20 * np.sin(ph + lag)) @ _rot("z", s * 8))
        elbow = shoulder + down * upper
        twist = lambda ph: Rotation.from_rotvec(np.outer(np.deg2rad(30 * np.sin(ph)), down)).as_matrix()
        if o["twist"]:
            ua = add(ua, shoulder + down * upper * 0.5, "upper_arm", side, "upper_twist", rot=twist)
        el = add(ua, elbow, "forearm", side, "forearm", rot=lambda ph: _rot("x", -25 - 15 * np.sin(ph + lag)))
        wrist = elbow + down * fore
        if o["twist"]:
            el = add(el, elbow + down * fore * 0.6, "forearm", side, "fore_twist", rot=twist)
        hand_rot = lambda ph: _rot("x", 10 * np.sin(2 * ph)) @ _rot("z", s * 6 * np.sin(ph))
        if not o["fingers"] and not (o["thumbs"] or o["hand_end"]):
            add(el, wrist, "hand", side, "hand", rot=hand_rot,
                end=[0, 0, 0] if zero else down * jit(0.09) * H)
            return
        if not o["fingers"]:  # a thumb and/or a tip joint under the hand (Hand_End of some exporters)
            hand = add(el, wrist, "hand", side, "hand", rot=hand_rot)
            if o["thumbs"]:
                base = wrist + [s * 0.012 * H, -0.015 * H, 0.012 * H]
                direction = np.array([s * 0.3, -0.6, 0.75]) / np.linalg.norm([0.3, 0.6, 0.75])
                add(hand, base, "finger", side, "thumb", rot=lambda ph: _rot("x", -(10 + 10 * np.sin(ph))),
                    end=direction * 0.03 * H)
            if o["hand_end"]:
                add(hand, wrist + down * 0.09 * H, "finger", side, "hand_end", rot=_still,
                    end=[0, 0, 0] if zero else down * 0.01 * H)
            return
        hand = add(el, wrist, "hand", side, "hand", rot=hand_rot)
        for f in range(5):
            if f == 0:  # thumb: forward and down
                base = wrist + [s * 0.012 * H, -0.015 * H, 0.012 * H]
                direction = np.array([s * 0.3, -0.6, 0.75])
                length = 0.017 * H
            else:
                base = wrist + [s * (0.018 - 0.009 * (f - 1)) * H * 0.6 + s * 0.004 * H, -0.05 * H, 0.012 * H - 0.008 * (f - 1) * H]
                direction = np.array([s * 0.05, -1.0, 0.0])
                length = (0.02 - 0.003 * abs(f - 2)) * H
            direction /= np.linalg.norm(direction)
            parent, p = hand, base
            for link in range(3):
                j = add(parent, p, "finger", side, f"finger{f}_{link}",
                        rot=lambda ph, f=f: _rot("x", -(10 + 10 * np.sin(ph + f))))
                parent, p = j, p + direction * length * (0.9 ** link)
            nodes[parent].end = direction * length * 0.5

    leg(1.0, "left")
    leg(-1.0, "right")
    n_spine = int(rng.integers(1, 4))
    parent = root
    top = nodes[root].pos
    for k in range(n_spine):
        top = top + [0, 0.24 * H / n_spine, 0.003 * H]
        parent = add(parent, top, "trunk", rot=lambda ph, k=k: _rot("y", -4 * np.sin(ph)) @ _rot("x", 2 + 0 * ph))
        prop_slots.append(parent)
    chest = parent
    arm(chest, 1.0, "left")
    arm(chest, -1.0, "right")
    neck_pos = nodes[chest].pos + [0, 0.06 * H, 0]
    neck = add(chest, neck_pos, "head", rot=swing("x", 4))
    head_pos = neck_pos + [0, 0.05 * H, 0.01 * H]
    head = add(neck, head_pos, "head", rot=lambda ph: _rot("y", 10 * np.sin(ph)) @ _rot("x", 5 * np.cos(ph)),
               end=[0, 0, 0] if zero else [0, jit(0.12) * H, 0])
    if o["face"]:
        for s, side in ((1.0, "left"), (-1.0, "right")):
            add(head, head_pos + [s * 0.018 * H, 0.05 * H, 0.05 * H], "face", side, "eye",
                rot=swing("y", 10), end=[0, 0, 0.01 * H])
        add(head, head_pos + [0, 0.01 * H, 0.02 * H], "face", rot=swing("x", 5, offset=5),
            end=[0, -0.03 * H, 0.045 * H])
    # Props: small leaves on the trunk, lengths far apart so that they never look like a pair.
    for n_prop in range(o["props"]):
        at = prop_slots[int(rng.integers(len(prop_slots)))]
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        d[2] = -abs(d[2])  # behind the body (a holster, a quiver)
        d /= np.linalg.norm(d)
        length = (0.02 if n_prop == 0 else 0.05) * H
        add(at, nodes[at].pos + 0.03 * H * np.array([0, 0, -1.0]), "detail", rot=swing("x", 3), end=d * length)

    # Reorder depth-first (children were appended after siblings' subtrees in places).
    children = [[] for _ in nodes]
    for k, n in enumerate(nodes):
        if n.parent >= 0:
            children[n.parent].append(k)
    order: list[int] = []
    stack = [0]
    while stack:
        k = stack.pop()
        order.append(k)
        stack.extend(reversed(children[k]))
    new_of = {old: new for new, old in enumerate(order)}
    nodes = [dataclasses.replace(nodes[old], parent=new_of.get(nodes[old].parent, -1)) for old in order]
    J = len(nodes)
    children = [[] for _ in nodes]
    for k, n in enumerate(nodes):
        if n.parent >= 0:
            children[n.parent].append(k)
    names = _names(rng, J + 1)
    marker_name = names.pop()
    for k, n in enumerate(nodes):
        n.name = names[k]

    # Motion in the canonical frame.
    T = int(o["frames"])
    ph = 2 * np.pi * np.arange(T) / period + rng.uniform(0, 2 * np.pi)
    A = np.stack([n.rot(ph) for n in nodes], axis=1)  # (T, J, 3, 3)
    root_pos = np.stack([np.zeros(T), pelvis_h + 0.01 * H * np.sin(2 * ph), speed * np.arange(T) / 30.0], axis=1)
    heading = rng.uniform(0, 360)
    W = _rot("y", heading)[0]
    if o["up"] == "Z":
        W = _rot("x", 90)[0] @ W
    up = W @ np.array([0, 1.0, 0])

    # Rest orientation of each joint: identity, or X along its main bone (a bent zero pose).
    Q = np.broadcast_to(np.eye(3), (J, 3, 3)).copy()
    if o["bent_zero_pose"]:
        for k, n in enumerate(nodes):
            if children[k]:
                d = nodes[max(children[k], key=lambda c: np.linalg.norm(nodes[c].pos - n.pos))].pos - n.pos
            elif n.end is not None and np.linalg.norm(n.end) > 0:
                d = n.end
            else:
                d = rng.normal(size=3)
            if np.linalg.norm(d) < 1e-9:
                d = rng.normal(size=3)
            Q[k] = _orthonormal_with_x(d, rng)
    offsets = np.zeros((J, 3))
    ends: list[np.ndarray | None] = []
    B = np.empty_like(A)
    for k, n in enumerate(nodes):
        if n.parent >= 0:
            offsets[k] = Q[n.parent].T @ (n.pos - nodes[n.parent].pos)
            B[:, k] = Q[n.parent].T @ A[:, k] @ Q[k]
        else:
            B[:, k] = W @ A[:, k] @ Q[k]
        ends.append(None if n.end is None else Q[k].T @ n.end)
    world_root_pos = root_pos @ W.T
    world_root_rot = B[:, 0]

    scale = o["scale"] / UNITS[o["unit"]]  # file units per metre
    orders = [str(rng.choice(ORDERS)) for _ in range(J + 1)]
    six = o["six_channels"]

    def euler(order, R):
        with warnings.catch_warnings():  # gimbal lock (a constant rest orientation): still a valid split
            warnings.simplefilter("ignore", UserWarning)
            return Rotation.from_matrix(R).as_euler(order, degrees=True)

    columns: list[np.ndarray] = []
    lines = ["HIERARCHY"]
    depth = 0
    marker = o["virtual_root"]
    if marker:
        # Ground marker: drifts and turns slowly; the body root's channels are relative to it.
        M_R = _rot("y", np.linspace(0, 15, T)) @ np.broadcast_to(np.eye(3), (T, 3, 3))
        M_R = np.einsum("ab,tbc,cd->tad", W, M_R, W.T)
        M_p = np.outer(np.linspace(0, 0.3, T), W @ [1.0, 0, 0.5])
        lines += ["ROOT " + marker_name, "{", "\tOFFSET 0 0 0",
                  f"\tCHANNELS 6 Xposition Yposition Zposition {' '.join(a + 'rotation' for a in orders[J])}"]
        columns += [M_p * scale, euler(orders[J], M_R)]
        rel_rot = np.swapaxes(M_R, 1, 2) @ world_root_rot
        rel_pos = np.einsum("tba,tb->ta", M_R, world_root_pos - M_p)
        depth = 1
    else:
        rel_rot, rel_pos = world_root_rot, world_root_pos

    open_stack: list[int] = []

    def close_to(parent: int) -> None:
        nonlocal lines
        while open_stack and open_stack[-1] != parent:
            k = open_stack.pop()
            pad = "\t" * (depth + len(open_stack))
            if ends[k] is not None:
                e = ends[k] * scale
                lines += [pad + "\tEnd Site", pad + "\t{", pad + f"\t\tOFFSET {e[0]:.9g} {e[1]:.9g} {e[2]:.9g}",
                          pad + "\t}"]
            lines.append(pad + "}")

    for k, n in enumerate(nodes):
        close_to(n.parent)
        pad = "\t" * (depth + len(open_stack))
        word = "ROOT" if (k == 0 and not marker) else "JOINT"
        off = (rel_pos[0] if k == 0 else offsets[k]) * scale
        rot_ch = " ".join(a + "rotation" for a in orders[k])
        if k == 0 or six:
            pos_vals = rel_pos if k == 0 else np.broadcast_to(offsets[k], (T, 3))
            lines += [pad + f"{word} {n.name}", pad + "{", pad + f"\tOFFSET {off[0]:.9g} {off[1]:.9g} {off[2]:.9g}",
                      pad + f"\tCHANNELS 6 Xposition Yposition Zposition {rot_ch}"]
            columns.append(pos_vals * scale)
        else:
            lines += [pad + f"{word} {n.name}", pad + "{", pad + f"\tOFFSET {off[0]:.9g} {off[1]:.9g} {off[2]:.9g}",
                      pad + f"\tCHANNELS 3 {rot_ch}"]
        columns.append(euler(orders[k], rel_rot if k == 0 else B[:, k]))
        open_stack.append(k)
    close_to(-1)
    if marker:
        lines.append("}")
    motion = np.concatenate(columns, axis=1)
    lines += ["MOTION", f"Frames: {T}", "Frame Time: 0.0333333"]
    lines += [" ".join(f"{v:.9g}" for v in row) for row in motion]
    text = "\n".join(lines) + "\n"

    role_index = {(n.role, n.side): k for k, n in enumerate(nodes) if n.role}
    other = {"left": "right", "right": "left"}
    mirror = [role_index.get((n.role, other[n.side]), -1) if n.role and n.side else -1 for n in nodes]
    return Rig(text=text, names=[n.name for n in nodes], segment=[n.segment for n in nodes],
               side=[n.side for n in nodes], mirror=mirror, up=np.round(up, 12), stature=H * o["scale"],
               unit=o["unit"], virtual_root=marker_name if marker else None, options=o)


def _bvh_layout(lines: list[str]):
    """Per CHANNELS line: (line index, channel names, first motion column); and the MOTION line."""
    out, col, motion = [], 0, None
    for i, line in enumerate(lines):
        words = line.split()
        if words and words[0] == "CHANNELS":
            names = words[2:]
            out.append((i, names, col))
            col += len(names)
        elif words and words[0] == "MOTION":
            motion = i
            break
    return out, motion


def reencode(text: str, orders) -> str:
    """The same BVH motion with each 3-rotation-channel joint's rotations written in another
    Euler order: ``orders`` a string (every joint) or a list, one per CHANNELS line (None keeps
    that joint's). Rotations by scipy (intrinsic, as BVH), angles written with 10 decimals."""
    lines = text.splitlines()
    layout, motion = _bvh_layout(lines)
    data = np.array([[float(x) for x in ln.split()] for ln in lines[motion + 3:] if ln.strip()])
    if isinstance(orders, str):
        orders = [orders] * len(layout)
    for (i, names, col), new in zip(layout, orders):
        rot = [k for k, n in enumerate(names) if n.lower().endswith("rotation")]
        if new is None or len(rot) != 3 or rot != list(range(rot[0], rot[0] + 3)):
            continue
        old = "".join(names[k][0].upper() for k in rot)
        cols = [col + k for k in rot]
        r = Rotation.from_euler(old, data[:, cols], degrees=True)
        with warnings.catch_warnings():  # at exact lock scipy picks one of the equivalent triples
            warnings.simplefilter("ignore", UserWarning)
            data[:, cols] = r.as_euler(new.upper(), degrees=True)
        for k, axis in zip(rot, new.upper()):
            names[k] = f"{axis}rotation"
        indent = lines[i][: len(lines[i]) - len(lines[i].lstrip())]
        lines[i] = f"{indent}CHANNELS {len(names)} " + " ".join(names)
    body = [" ".join(f"{x:.10f}" for x in row) for row in data]
    return "\n".join(lines[: motion + 3] + body) + "\n"


def middle_angles(text: str, order: str) -> np.ndarray:
    """(T, joints) middle Euler angle (deg) of every 3-rotation joint written in ``order``:
    +-90 is gimbal lock."""
    lines = text.splitlines()
    layout, motion = _bvh_layout(lines)
    data = np.array([[float(x) for x in ln.split()] for ln in lines[motion + 3:] if ln.strip()])
    out = []
    for _, names, col in layout:
        rot = [k for k, n in enumerate(names) if n.lower().endswith("rotation")]
        if len(rot) != 3:
            out.append(np.zeros(len(data)))
            continue
        old = "".join(names[k][0].upper() for k in rot)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            out.append(Rotation.from_euler(old, data[:, [col + k for k in rot]], degrees=True).as_euler(order)[:, 1])
    return np.degrees(np.stack(out, -1))


def spin_root(text: str, rate: float, up: str = "Y") -> str:
    """The motion turned about the world up axis at ``rate`` rad/s (root position and rotation
    both), so the root spins fast while the body moves as before."""
    lines = text.splitlines()
    layout, motion = _bvh_layout(lines)
    ft = float(lines[motion + 2].split(":")[1])
    data = np.array([[float(x) for x in ln.split()] for ln in lines[motion + 3:] if ln.strip()])
    _, names, col = layout[0]
    pos = [col + k for k, n in enumerate(names) if n.lower().endswith("position")]
    rot = [k for k, n in enumerate(names) if n.lower().endswith("rotation")]
    order = "".join(names[k][0].upper() for k in rot)
    rcols = [col + k for k in rot]
    turn = Rotation.from_rotvec(np.outer(rate * ft * np.arange(len(data)), np.eye(3)["XYZ".index(up.upper())]))
    data[:, pos] = turn.apply(data[:, pos])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        data[:, rcols] = (turn * Rotation.from_euler(order, data[:, rcols], degrees=True)).as_euler(order, degrees=True)
    body = [" ".join(f"{x:.10f}" for x in row) for row in data]
    return "\n".join(lines[: motion + 3] + body) + "\n"


def chain_text(links: int = 3, frames: int = 40) -> str:
    """A BVH chain of ``links`` links under a 6-channel root, swaying: no limbs, so the anatomy
    labels every joint trunk (a rig without arms, legs or head)."""
    text = ["HIERARCHY", "ROOT Base", "{", "OFFSET 0 0 0",
            "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    for k in range(links):
        text += [f"JOINT Seg{k + 1}", "{", "OFFSET 0 0.3 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    text += ["End Site", "{", "OFFSET 0 0.3 0", "}"] + ["}"] * (links + 1)
    motion = [[0, 0.5, 0, 0, 0, 0] + list(10 * np.sin(0.2 * t + np.arange(3 * links))) for t in range(frames)]
    text += ["MOTION", f"Frames: {frames}", "Frame Time: 0.0333333"]
    text += [" ".join(f"{v:.4f}" for v in row) for row in motion]
    return "\n".join(text) + "\n"
