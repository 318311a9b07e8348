"""Collision shapes: capsules fitted to each body's polyhedron (body frame).

One capsule per bone that the mass model wrapped with a prism: axis = the bone (joint origin to
child joint or End Site), radius = the largest distance from that bone of the hull vertices
nearest to it (the prism's circumradius; the capsule contains the prism and adds round end
caps). A body without a counted bone gets one capsule along its shape's principal axis.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.model.skeleton import Character

MIN_CAPSULE_BONE = 0.03  # m: shorter bones get no capsule of their own
_TINY = 1e-12


class Capsules(eqx.Module):
    """Collision capsules fitted to the bodies (body frame, relative to the joint origin)."""

    body: Int[Array, " K"]
    a: Float[Array, "K 3"]
    b: Float[Array, "K 3"]
    radius: Float[Array, " K"]
    names: tuple[str, ...] = eqx.field(static=True)


def _bones(model, k: int, offsets, ends) -> list[np.ndarray]:
    """Bone vectors of the body at joint k at least ``MIN_CAPSULE_BONE`` long: to each child joint
    and to its End Site."""
    bones = [offsets[c] for c, p in enumerate(model.joint_parent) if p == k]
    if k in ends:
        bones.append(ends[k])
    return [e for e in bones if np.linalg.norm(e) >= MIN_CAPSULE_BONE]


def _body_capsules(name: str, verts, bones) -> list[tuple]:
    """``(a, b, radius, name)`` of one body's capsules: one per bone, radius the largest distance
    of the vertices nearest that bone; the principal-axis capsule when it has no bone."""
    if not bones:
        a, e, r = _principal_capsule(verts)
        return [(a, e, r, name)]
    dist = np.stack([segment_distances(verts, np.zeros(3), e) for e in bones], 1)
    nearest = np.argmin(dist, 1)
    out = []
    for i, e in enumerate(bones):
        mine = dist[nearest == i, i]
        r = float(mine.max()) if mine.size else float(dist[:, i].min())
        out.append((np.zeros(3), np.asarray(e, np.float64), r, f"{name}[{i}]" if len(bones) > 1 else name))
    return out


def fit_capsules(character: Character) -> Capsules:
    """Capsules fitted to each body's polyhedron: one per bone of the body (to a child joint or
    End Site, at least ``MIN_CAPSULE_BONE`` long), radius the largest distance of the vertices
    nearest that bone; a body without such a bone (a hand, foot or skull whose End Site has zero
    length) gets one capsule along its shape's principal axis."""
    model = character.model
    offsets = np.asarray(model.joint_offset)
    ends = {k: np.asarray(model.end_site_offset[i]) for i, k in enumerate(model.end_site_joint)}
    body, caps = [], []
    for b, k in enumerate(model.body_joint):
        shape = character.shapes[b]
        assert shape is not None, f"body {model.body_names[b]} has no polyhedron"
        verts = np.asarray(shape.vertices, np.float64)
        mine = _body_capsules(model.body_names[b], verts, _bones(model, k, offsets, ends))
        body += [b] * len(mine)
        caps += mine
    aa, bb, rr, names = zip(*caps)
    return Capsules(
        jnp.asarray(body, jnp.int32),
        jnp.asarray(np.stack(aa)),
        jnp.asarray(np.stack(bb)),
        jnp.asarray(rr),
        tuple(names),
    )


def _principal_capsule(verts):
    """(a, b, radius) of a capsule along the principal axis of a vertex cloud that covers every
    vertex: radius the largest distance from the axis, end points at the extremes along it."""
    centre = verts.mean(0)
    _, _, vt = np.linalg.svd(verts - centre, full_matrices=False)
    axis = vt[0]
    t = (verts - centre) @ axis
    r = float(np.linalg.norm((verts - centre) - np.outer(t, axis), axis=1).max())
    return centre + float(t.min()) * axis, centre + float(t.max()) * axis, r


def segment_distances(points, a, b) -> np.ndarray:
    """Distance of each point (N, 3) from the segment a-b (numpy, for fitting)."""
    seg = b - a
    t = np.clip((points - a) @ seg / max(seg @ seg, _TINY), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * seg), axis=1)
