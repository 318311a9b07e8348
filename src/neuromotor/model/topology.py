"""The static structure of a skeleton: index arrays of its joint tree and body tree, built once.

Everything here depends only on the static tuples of :class:`~neuromotor.model.skeleton.Model`
(parents, rotation orders, DOF layout), never on array values, so one :class:`Topology` is built
per skeleton shape and cached (``Model.topology``). Per-joint work then becomes one gather or one
batched op over all joints instead of a Python loop of tiny ops (a traced loop made the step tens
of thousands of HLO ops and compile for about a minute).

Users: forward kinematics and Euler decompositions (``model.kinematics``), the body-tree gathers
and scatters of Eq. 1 (``physics.system``), the layout of Eq. 3 (``physics.inverse``), and the
tree and null-space solvers of Eq. 2 (``physics.solvers``).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class Topology:
    """Static (numpy) index data of one skeleton (hashable by identity; one per shape)."""

    # -- body tree (simulation)
    body_parent: tuple[int, ...]
    dof_body: tuple[int, ...]  # the child body each simulated DOF turns
    joint_dofs: np.ndarray  # (C, 3): DOF indices of each non-root body, slot order
    child: np.ndarray  # (C,): body of each joint row (1..B-1)
    parent: np.ndarray  # (C,): its parent body
    parent0: np.ndarray  # (B,): parent of each body, 0 for the root
    groups: tuple  # per rotation order: (order, bodies, their rows in the per-joint arrays)
    depth: np.ndarray  # (B,): depth of each body (root 0)
    contiguous: bool  # DOF layout is body-major and slot-ordered: (C, 3) reshapes to (n,)
    anc: np.ndarray  # (B, B): anc[i, k] = 1 if k is i or an ancestor of i
    levels: tuple[np.ndarray, np.ndarray]  # (L, W) joint rows and parents, deepest level first
    # -- joint tree (mocap kinematics)
    rotating: np.ndarray  # joints with rotation channels (the root first)
    local_row: np.ndarray  # row of each joint's local rotation in [quaternion rotations; identity]
    joint_depth: np.ndarray  # (J,): depth of each joint (roots 0)
    all_rotate: bool
    euler: tuple  # per rotation order: (order, joints, their (m, 3) columns in the angles block)
    n_all: int  # rotation channels of all non-root joints
    dof_columns: tuple[tuple[int, ...], ...]  # per joint, its columns in the angles block
    _derived: dict = dataclasses.field(default_factory=dict, repr=False)

    def derived(self, fn, *args):
        """``fn(self, *args)``, computed once per topology: the home of static layouts that belong
        to one equation's module (the placement of Eq. 3, the null-space basis of Eq. 2)."""
        key = (fn, args)
        if key not in self._derived:
            self._derived[key] = fn(self, *args)
        return self._derived[key]

    @property
    def n_bodies(self) -> int:
        return len(self.body_parent)

    @property
    def sel_child(self) -> np.ndarray:
        """(C, B) one-hot of each joint's child body (sums without scatter under vmap)."""
        return np.eye(self.n_bodies)[self.child]

    @property
    def sel_parent(self) -> np.ndarray:
        """(C, B) one-hot of each joint's parent body."""
        return np.eye(self.n_bodies)[self.parent]


def _depths(parents: tuple[int, ...]) -> np.ndarray:
    depth = np.zeros(len(parents), dtype=np.int64)
    for k, p in enumerate(parents):  # a parent precedes its children
        depth[k] = depth[p] + 1 if p >= 0 else 0
    return depth


def _ancestors(body_parent: tuple[int, ...]) -> np.ndarray:
    n = len(body_parent)
    anc = np.zeros((n, n))
    for i in range(n):
        k = i
        while k >= 0:
            anc[i, k] = 1.0
            k = body_parent[k]
    return anc


def _levels(body_parent: tuple[int, ...], depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elimination schedule, deepest level first, padded to equal width: joint rows (body - 1)
    and their parent bodies. Padding points at a ghost joint row C whose parent is a ghost body
    B, so every level is the same batched operation inside one ``lax.scan``."""
    n = len(body_parent)
    top = int(depth.max()) if n else 0
    per_level = [[b - 1 for b in range(1, n) if depth[b] == d] for d in range(top, 0, -1)]
    width = max((len(x) for x in per_level), default=1)
    rows = np.full((len(per_level), width), n - 1, dtype=np.int64)
    parents = np.full((len(per_level), width), n, dtype=np.int64)
    for i, level in enumerate(per_level):
        rows[i, : len(level)] = level
        parents[i, : len(level)] = [body_parent[r + 1] for r in level]
    return rows, parents


def _dof_columns(joint_parent: tuple[int, ...], joint_order: tuple[str, ...]) -> tuple[tuple[int, ...], ...]:
    out: list[tuple[int, ...]] = []
    start = 0
    for k, order in enumerate(joint_order):
        if joint_parent[k] < 0:
            out.append(())
            continue
        out.append(tuple(range(start, start + len(order))))
        start += len(order)
    return tuple(out)


def _grouped(keys, items) -> dict:
    groups: dict = {}
    for key, item in zip(keys, items):
        groups.setdefault(key, []).append(item)
    return groups


def _body_tree(body_parent, dof_body, body_orders) -> dict:
    n = len(body_parent)
    dofs = [tuple(i for i, db in enumerate(dof_body) if db == b) for b in range(n)]
    for b in range(1, n):
        if len(dofs[b]) != 3:
            raise ValueError(f"body {b} has {len(dofs[b])} simulated DOFs; ball joints need three")
    joint_dofs = np.array(dofs[1:], dtype=np.int64).reshape(n - 1, 3)
    groups = _grouped(body_orders[1:], range(1, n))
    depth = _depths(body_parent)
    return dict(
        joint_dofs=joint_dofs,
        child=np.arange(1, n),
        parent=np.array(body_parent[1:], dtype=np.int64),
        parent0=np.array([max(p, 0) for p in body_parent], dtype=np.int64),
        groups=tuple((o, np.array(bs), np.array(bs) - 1) for o, bs in groups.items()),
        depth=depth,
        contiguous=bool(np.array_equal(joint_dofs.reshape(-1), np.arange(len(dof_body)))),
        anc=_ancestors(body_parent),
        levels=_levels(body_parent, depth),
    )


def _joint_tree(joint_parent, joint_order) -> dict:
    n = len(joint_parent)
    rotating = [k for k, order in enumerate(joint_order) if order]
    local_row = np.full(n, len(rotating), dtype=np.int64)
    local_row[rotating] = np.arange(len(rotating))
    cols = _dof_columns(joint_parent, joint_order)
    moving = [k for k in range(n) if joint_parent[k] >= 0 and joint_order[k]]
    groups = _grouped([joint_order[k] for k in moving], moving)
    euler = tuple(
        (order, np.array(ks), np.array([cols[k] for k in ks], dtype=np.int64)) for order, ks in groups.items()
    )
    return dict(
        rotating=np.array(rotating, dtype=np.int64),
        local_row=local_row,
        joint_depth=_depths(joint_parent),
        all_rotate=len(rotating) == n,
        euler=euler,
        n_all=sum(len(c) for c in cols),
        dof_columns=cols,
    )


@functools.lru_cache(maxsize=64)
def build(
    body_parent: tuple[int, ...],
    dof_body: tuple[int, ...],
    body_orders: tuple[str, ...],
    joint_parent: tuple[int, ...],
    joint_order: tuple[str, ...],
) -> Topology:
    """The :class:`Topology` of these static tuples (cached: one object per skeleton shape)."""
    return Topology(
        body_parent=tuple(body_parent),
        dof_body=tuple(dof_body),
        **_body_tree(body_parent, dof_body, body_orders),
        **_joint_tree(joint_parent, joint_order),
    )


def of(model) -> Topology:
    """The topology of a :class:`~neuromotor.model.skeleton.Model` (``model.topology``)."""
    orders = tuple(model.joint_order[j] for j in model.body_joint)
    return build(model.body_parent, model.dof_body, orders, model.joint_parent, model.joint_order)


def of_tree(body_parent: tuple[int, ...]) -> Topology:
    """The topology of a bare body tree of ball joints (one joint per body, three DOFs each, XYZ):
    for solvers and tests that need the tree only."""
    n = len(body_parent)
    dof_body = tuple(b for b in range(1, n) for _ in range(3))
    return build(tuple(body_parent), dof_body, ("XYZ",) * n, tuple(body_parent), ("XYZ",) * n)
