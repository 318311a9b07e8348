"""glTF 2.0 export of a run: the body shapes on a skinned skeleton, the perturbed and the
unperturbed motion as two animations (docs/gltf.md).

Layout of the file (``.glb`` binary, or ``.gltf`` with the buffer embedded as a data URI):

* one joint node per body, flat under a root node (``<prefix>root``), whose translation and
  rotation are the body's world pose (COM position, orientation) after the axis change below.
  The simulated joints are soft (``constraint_violation`` > 0), so a parent-relative hierarchy
  would still need a translation per joint; world poses store exactly what was simulated, and
  every keyframe equals ``body_pos``/``body_quat`` to float32 rounding;
* one skinned mesh with a primitive and a PBR material per body, each vertex bound with weight
  1 to its body's joint. The bind pose is the first frame: ``POSITION`` holds the first frame's
  world vertices and the inverse bind matrices undo the first frame's body poses;
* animation ``"perturbed"`` drives the character (and the ball, when the run has one);
  animation ``"unperturbed"`` drives a translucent second copy, the ghost (``Layout.GHOST``), or
  the same joints (``Layout.SHARED``: switch between the two motions of one character);
* Y up as glTF requires: the whole scene is turned so that the clip's up axis becomes +Y, a
  proper rotation (X up: +90 deg about Z; Z up: -90 deg about X, Blender's own convention);
* keyframe times are the run's ``time - time[0]`` (s), LINEAR interpolation, lengths in metres;
  glTF quaternions are x y z w (RUN.npz stores w x y z).
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import json
import pathlib
import re
import struct

import numpy as np

from neuromotor.atomic import atomic_path
from neuromotor.errors import UserError
from neuromotor.io.palette import COLOR_BALL, COLOR_GHOST, COLOR_PERTURBED
from neuromotor.io.runfile import SHAPE_FIELDS, read_run

GLTF_SUFFIXES = (".glb", ".gltf")
FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
GHOST_ALPHA = 0.35
_S = np.sqrt(0.5)
# w x y z of the rotation taking the clip's up axis (0, 1, 2) to +Y.
UP_TO_Y = {0: np.array([_S, 0.0, 0.0, _S]), 1: np.array([1.0, 0.0, 0.0, 0.0]), 2: np.array([_S, -_S, 0.0, 0.0])}


class Layout(enum.Enum):
    """Where the unperturbed motion goes."""

    GHOST = "ghost"  # a translucent second copy of the character
    SHARED = "shared"  # the same joints as the perturbed motion


# ----------------------------------------------------------------------------------------------
# Poses in glTF's frame
# ----------------------------------------------------------------------------------------------


def quat_mul_wxyz(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p q of w x y z quaternions (broadcasting)."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        -1,
    )


def quat_matrix_wxyz(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit w x y z quaternions (..., 3, 3)."""
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def continuous_quats(quat: np.ndarray) -> np.ndarray:
    """Quaternions (T, ..., 4) with the sign of each keyframe chosen so that consecutive ones
    have a positive dot product (q and -q are the same rotation; LINEAR interpolation of the
    components, as some importers do, then takes the short way)."""
    flip = np.sum(quat[1:] * quat[:-1], axis=-1) < 0
    sign = np.concatenate([np.ones((1,) + flip.shape[1:]), np.where(flip, -1.0, 1.0)])
    return quat * np.cumprod(sign, axis=0)[..., None]


def y_up_poses(pos: np.ndarray, quat: np.ndarray, up_axis: int) -> tuple[np.ndarray, np.ndarray]:
    """World poses turned so that ``up_axis`` becomes +Y: p' = R_up p, q' = q_up q (w x y z)."""
    q_up = UP_TO_Y[up_axis]
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return pos @ quat_matrix_wxyz(q_up).T, continuous_quats(quat_mul_wxyz(q_up, quat))


def xyzw(quat_wxyz: np.ndarray) -> np.ndarray:
    """glTF's component order x y z w."""
    return np.concatenate([quat_wxyz[..., 1:], quat_wxyz[..., :1]], -1)


# ----------------------------------------------------------------------------------------------
# Binary buffer and accessors
# ----------------------------------------------------------------------------------------------

_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
_DTYPES = {FLOAT: np.float32, UBYTE: np.uint8, USHORT: np.uint16, UINT: np.uint32}


@dataclasses.dataclass
class _Buffer:
    """The one binary buffer: a buffer view and an accessor per array, 4-byte aligned."""

    data: bytearray = dataclasses.field(default_factory=bytearray)
    views: list = dataclasses.field(default_factory=list)
    accessors: list = dataclasses.field(default_factory=list)

    def add(self, array, component: int, target: int | None = None, bounds: bool = False, matrix: bool = False) -> int:
        """Append ``array`` (N,) or (N, k) as ``component`` values; the accessor's index."""
        a = np.ascontiguousarray(np.asarray(array).astype(_DTYPES[component]))
        width = 16 if matrix else (a.shape[1] if a.ndim == 2 else 1)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": a.nbytes}
        if target is not None:
            view["target"] = target
        self.data += a.tobytes() + b"\0" * (-a.nbytes % 4)
        self.views.append(view)
        acc = {
            "bufferView": len(self.views) - 1,
            "componentType": component,
            "count": int(a.shape[0]),
            "type": _TYPES[width],
        }
        if bounds:  # required for POSITION and animation inputs
            flat = a.reshape(a.shape[0], -1)
            acc["min"], acc["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


# ----------------------------------------------------------------------------------------------
# Scene content
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class GltfRun:
    """What the file shows, in glTF's frame (Y up, metres, seconds from 0)."""

    time: np.ndarray  # (T,) s, starting at 0
    names: tuple[str, ...]  # (B,) body names
    vertices: np.ndarray  # (V, 3) body frame less COM
    faces: np.ndarray  # (F, 3)
    owner: np.ndarray  # (V,) body of each vertex
    pose: tuple[np.ndarray, np.ndarray]  # perturbed (T, B, 3), (T, B, 4 w x y z)
    pose_base: tuple[np.ndarray, np.ndarray]  # unperturbed
    ball: np.ndarray | None  # (T, 3) or None
    ball_radius: float
    up_axis: int
    time_offset: float


def load_gltf_run(run_path) -> GltfRun:
    """The arrays of a RUN.npz that the export needs; :class:`UserError` naming the file and field."""
    d = read_run(run_path, fields=("time",) + SHAPE_FIELDS)
    if d["shape_vertices"].shape[0] == 0 or d["shape_faces"].shape[0] == 0:
        raise UserError(f"{run_path}: field 'shape_vertices' is empty (the run has no body shapes to export)")
    up = int(d.get("up_axis", 1))
    B = d["body_pos"].shape[1]
    given = d.get("body_names")
    names = (
        tuple(str(n) for n in given)
        if given is not None and given.shape == (B,)
        else tuple(f"body{b}" for b in range(B))
    )
    ball = d.get("ball_pos")
    return GltfRun(
        time=d["time"] - d["time"][0],
        names=names,
        vertices=np.asarray(d["shape_vertices"], float),
        faces=d["shape_faces"],
        owner=d["shape_body"],
        pose=y_up_poses(d["body_pos"], d["body_quat"], up),
        pose_base=y_up_poses(d["body_pos_unperturbed"], d["body_quat_unperturbed"], up),
        ball=None if ball is None else ball @ quat_matrix_wxyz(UP_TO_Y[up]).T,
        ball_radius=float(d.get("ball_radius", 0.0)),
        up_axis=up,
        time_offset=float(d["time"][0]),
    )


def body_side(name: str) -> int:
    """+1 for a left body, -1 for a right one, 0 otherwise, from its name (``LeftArm``,
    ``mixamorig:RightLeg``, ``L_Hip``, ``lShldr``, ``hip.R``)."""
    for sign, word, letter in ((1, "left", "l"), (-1, "right", "r")):
        if (
            word in name.lower()
            or re.match(rf"[{letter}{letter.upper()}]([_.]|[A-Z])", name)
            or re.search(rf"[_.]{letter}$", name, re.IGNORECASE)
        ):
            return sign
    return 0


def body_colors(names) -> np.ndarray:
    """(B, 3) linear RGB per body: the perturbed orange, lighter on the left, darker on the right,
    stepped along the body list so that neighbours differ."""
    base = np.asarray(COLOR_PERTURBED)
    out = []
    for b, name in enumerate(names):
        shade = 0.25 * body_side(name) + 0.08 * ((b % 3) - 1)
        rgb = base + shade * (1.0 - base) if shade > 0 else base * (1.0 + shade)
        out.append(np.clip(rgb, 0.0, 1.0) ** 2.2)  # sRGB -> linear, as baseColorFactor is linear
    return np.asarray(out)


def uv_sphere(radius: float, rings: int = 8, segments: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and outward triangles of a UV sphere (poles shared)."""
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), -np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]]) * radius
    idx = lambda r, s: 1 + r * segments + s % segments
    faces = [(0, idx(0, s), idx(0, s + 1)) for s in range(segments)]
    for r in range(rings - 2):
        for s in range(segments):
            faces += [(idx(r, s), idx(r + 1, s), idx(r + 1, s + 1)), (idx(r, s), idx(r + 1, s + 1), idx(r, s + 1))]
    last = len(verts) - 1
    faces += [(last, idx(rings - 2, s + 1), idx(rings - 2, s)) for s in range(segments)]
    return verts, np.asarray(faces)


# ----------------------------------------------------------------------------------------------
# Document
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Doc:
    """The glTF JSON being assembled, with its buffer."""

    buf: _Buffer = dataclasses.field(default_factory=_Buffer)
    nodes: list = dataclasses.field(default_factory=list)
    meshes: list = dataclasses.field(default_factory=list)
    materials: list = dataclasses.field(default_factory=list)
    skins: list = dataclasses.field(default_factory=list)
    roots: list = dataclasses.field(default_factory=list)

    def node(self, **fields) -> int:
        self.nodes.append(fields)
        return len(self.nodes) - 1

    def material(self, name: str, rgb, alpha: float = 1.0) -> int:
        m = {
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [*map(float, rgb), alpha],
                "metallicFactor": 0.0,
                "roughnessFactor": 0.8,
            },
        }
        if alpha < 1.0:
            m["alphaMode"] = "BLEND"
        self.materials.append(m)
        return len(self.materials) - 1


def _trs(pos, quat) -> dict:
    return {"translation": [float(x) for x in pos], "rotation": [float(x) for x in xyzw(quat)]}


def _skeleton(doc: _Doc, run: GltfRun, pose, prefix: str) -> list[int]:
    """Joint nodes (one per body, at the first frame's pose) under a root; their indices."""
    pos, quat = pose
    joints = [doc.node(name=f"{prefix}{n}", **_trs(pos[0, b], quat[0, b])) for b, n in enumerate(run.names)]
    doc.roots.append(doc.node(name=f"{prefix}root", children=joints))
    return joints


def _bind_matrices(pos0: np.ndarray, quat0: np.ndarray) -> np.ndarray:
    """(B, 16) column-major inverse bind matrices [R^T, -R^T p] of the first frame's poses."""
    rt = np.swapaxes(quat_matrix_wxyz(quat0), -1, -2)
    m = np.zeros((len(pos0), 4, 4))
    m[:, :3, :3], m[:, :3, 3], m[:, 3, 3] = rt, -np.einsum("bij,bj->bi", rt, pos0), 1.0
    return np.swapaxes(m, -1, -2).reshape(len(pos0), 16)  # column-major


def _mesh_attributes(doc: _Doc, run: GltfRun) -> dict:
    """POSITION (first-frame world vertices), JOINTS_0 and WEIGHTS_0 (one body per vertex)."""
    pos0, quat0 = run.pose[0][0], run.pose[1][0]
    rot0 = quat_matrix_wxyz(quat0)
    world = pos0[run.owner] + np.einsum("vij,vj->vi", rot0[run.owner], run.vertices)
    joints = np.zeros((len(world), 4), np.int64)
    joints[:, 0] = run.owner
    weights = np.zeros((len(world), 4))
    weights[:, 0] = 1.0
    return {
        "POSITION": doc.buf.add(world, FLOAT, ARRAY_BUFFER, bounds=True),
        "JOINTS_0": doc.buf.add(joints, UBYTE if len(run.names) < 256 else USHORT, ARRAY_BUFFER),
        "WEIGHTS_0": doc.buf.add(weights, FLOAT, ARRAY_BUFFER),
    }


def _character(doc: _Doc, run: GltfRun, ghost: bool) -> dict:
    """The skinned character meshes: per-body materials, and a translucent ghost when asked.
    Returns the joint node indices per copy ("perturbed", "unperturbed")."""
    attrs = _mesh_attributes(doc, run)
    ibm = doc.buf.add(_bind_matrices(run.pose[0][0], run.pose[1][0]), FLOAT, matrix=True)
    face_body = run.owner[run.faces[:, 0]]
    prims = []
    for b, rgb in enumerate(body_colors(run.names)):
        f = run.faces[face_body == b]
        if len(f):
            prims.append(
                {
                    "attributes": attrs,
                    "indices": doc.buf.add(f.reshape(-1), UINT, ELEMENT_ARRAY_BUFFER),
                    "material": doc.material(run.names[b], rgb),
                }
            )
    doc.meshes.append({"name": "character", "primitives": prims})
    joints = {"perturbed": _skeleton(doc, run, run.pose, "")}
    doc.skins.append(
        {"name": "skeleton", "joints": joints["perturbed"], "inverseBindMatrices": ibm, "skeleton": doc.roots[-1]}
    )
    doc.roots.append(doc.node(name="character", mesh=0, skin=0))
    if not ghost:
        joints["unperturbed"] = joints["perturbed"]
        return joints
    prim = {
        "attributes": attrs,
        "indices": doc.buf.add(run.faces.reshape(-1), UINT, ELEMENT_ARRAY_BUFFER),
        "material": doc.material("ghost", np.asarray(COLOR_GHOST) ** 2.2, GHOST_ALPHA),
    }
    doc.meshes.append({"name": "ghost", "primitives": [prim]})
    joints["unperturbed"] = _skeleton(doc, run, run.pose_base, "ghost_")
    doc.skins.append(
        {
            "name": "ghost_skeleton",
            "joints": joints["unperturbed"],
            "inverseBindMatrices": ibm,
            "skeleton": doc.roots[-1],
        }
    )
    doc.roots.append(doc.node(name="ghost", mesh=1, skin=1))
    return joints


def _ball(doc: _Doc, run: GltfRun) -> int:
    """The ball's node (a UV sphere at its first position)."""
    assert run.ball is not None  # called for runs with a ball
    verts, faces = uv_sphere(run.ball_radius)
    prim = {
        "attributes": {"POSITION": doc.buf.add(verts, FLOAT, ARRAY_BUFFER, bounds=True)},
        "indices": doc.buf.add(faces.reshape(-1), UINT, ELEMENT_ARRAY_BUFFER),
        "material": doc.material("ball", np.asarray(COLOR_BALL) ** 2.2),
    }
    doc.meshes.append({"name": "ball", "primitives": [prim]})
    doc.roots.append(doc.node(name="ball", mesh=len(doc.meshes) - 1, translation=[float(x) for x in run.ball[0]]))
    return doc.roots[-1]


def _animation(doc: _Doc, name: str, t_acc: int, tracks) -> dict:
    """An animation of (node, path, values) tracks, all sampled at the accessor ``t_acc``."""
    samplers, channels = [], []
    for node, path, values in tracks:
        samplers.append({"input": t_acc, "output": doc.buf.add(values, FLOAT), "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})
    return {"name": name, "samplers": samplers, "channels": channels}


def _pose_tracks(joints, pose) -> list:
    pos, quat = pose
    return [t for b, j in enumerate(joints) for t in ((j, "translation", pos[:, b]), (j, "rotation", xyzw(quat[:, b])))]


def build_gltf(run: GltfRun, layout: Layout = Layout.GHOST) -> tuple[dict, bytes]:
    """The glTF JSON (without ``buffers``) and its binary buffer."""
    from neuromotor import __version__

    doc = _Doc()
    joints = _character(doc, run, layout is Layout.GHOST)
    ball = _ball(doc, run) if run.ball is not None else None
    t_acc = doc.buf.add(run.time, FLOAT, bounds=True)
    pert = _pose_tracks(joints["perturbed"], run.pose)
    if ball is not None:
        pert.append((ball, "translation", run.ball))
    animations = [
        _animation(doc, "perturbed", t_acc, pert),
        _animation(doc, "unperturbed", t_acc, _pose_tracks(joints["unperturbed"], run.pose_base)),
    ]
    gltf = {
        "asset": {"version": "2.0", "generator": f"neuromotor {__version__}"},
        "scene": 0,
        "scenes": [
            {
                "name": "run",
                "nodes": doc.roots,
                "extras": {"source_up_axis": run.up_axis, "time_offset_s": run.time_offset, "layout": layout.value},
            }
        ],
        "nodes": doc.nodes,
        "meshes": doc.meshes,
        "materials": doc.materials,
        "skins": doc.skins,
        "animations": animations,
        "accessors": doc.buf.accessors,
        "bufferViews": doc.buf.views,
    }
    return gltf, bytes(doc.buf.data)


# ----------------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------------


def glb_bytes(gltf: dict, binary: bytes) -> bytes:
    """A GLB container: 12-byte header, the JSON chunk (space padded), the BIN chunk (zero padded)."""
    doc = json.dumps({**gltf, "buffers": [{"byteLength": len(binary)}]}, separators=(",", ":")).encode()
    doc += b" " * (-len(doc) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<I4s", len(doc), b"JSON") + doc + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def gltf_text(gltf: dict, binary: bytes) -> bytes:
    """A .gltf JSON file with the buffer embedded as a base64 data URI."""
    uri = "data:application/octet-stream;base64," + base64.b64encode(binary).decode("ascii")
    return json.dumps({**gltf, "buffers": [{"byteLength": len(binary), "uri": uri}]}, indent=1).encode()


def export_gltf(run_path, out_path, layout: Layout = Layout.GHOST) -> pathlib.Path:
    """Write RUN.npz's bodies and both motions as ``.glb`` or ``.gltf`` (module docstring)."""
    out = pathlib.Path(out_path)
    if out.suffix.lower() not in GLTF_SUFFIXES:
        raise UserError(f"{out}: output must end in .glb or .gltf, got {out.suffix or 'no extension'!r}")
    gltf, binary = build_gltf(load_gltf_run(run_path), layout)
    data = glb_bytes(gltf, binary) if out.suffix.lower() == ".glb" else gltf_text(gltf, binary)
    with atomic_path(out) as tmp:
        pathlib.Path(tmp).write_bytes(data)
    return out
