"""Mesh-building primitives for the built-in avatar: lofted surfaces (capsules, ellipsoids, torsos) and a part list.

A loft is a stack of cross-section rings around a centre line, closed by a pole vertex at each end. Every
ring is an ellipse (or a superellipse for boxy parts) in the plane spanned by `side` and `front`. Rings
share their first and last vertex (no seam duplicates), so smooth vertex normals have no seam line.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Part:
    """One piece of the avatar: rest vertices, faces, skinning weights and colours.

    vertices (n, 3) metres; faces (m, 3) vertex ids local to the part; weights (n, J) rows sum to 1;
    colours (n, 3) in [0, 1]; `attributes` holds extra per-vertex arrays (n, ...) used by the blendshapes.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    colours: np.ndarray
    attributes: dict = field(default_factory=dict)


def superellipse(angles: np.ndarray, exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit superellipse |x|^e + |y|^e = 1 sampled at `angles`; exponent 2 is the ellipse."""
    cos, sin = np.cos(angles), np.sin(angles)
    power = 2.0 / exponent
    return np.sign(cos) * np.abs(cos) ** power, np.sign(sin) * np.abs(sin) ** power


def loft(
    centers: np.ndarray,
    half_side: np.ndarray,
    half_front: np.ndarray,
    side: np.ndarray,
    front: np.ndarray,
    n_around: int,
    exponent: float = 2.0,
    phase: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Closed lofted surface through K rings, with pole vertices at centers[0] and centers[-1].

    centers (K, 3); half_side, half_front (K,) ring radii (the first and last are ignored: they are poles);
    side, front (3,) orthonormal ring axes. Returns vertices (2 + (K-2)*n_around, 3) and outward faces.
    Vertex order: pole 0, ring 1 (n_around), ..., ring K-2, pole K-1; ring angle a has point
    center + half_side*cos(a)*side + half_front*sin(a)*front.
    """
    angles = phase + np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    u, v = superellipse(angles, exponent)
    inner = slice(1, len(centers) - 1)
    rings = (
        centers[inner, None, :]
        + half_side[inner, None, None] * u[None, :, None] * side
        + half_front[inner, None, None] * v[None, :, None] * front
    )  # (K-2, n, 3)
    vertices = np.concatenate([centers[:1], rings.reshape(-1, 3), centers[-1:]])
    return vertices, ring_faces(len(centers) - 2, n_around, outward=_winding_outward(centers, side, front))


def _winding_outward(centers: np.ndarray, side: np.ndarray, front: np.ndarray) -> bool:
    """True when the rings run along +(side x front), which makes `ring_faces` point outward."""
    return float(np.dot(centers[-1] - centers[0], np.cross(side, front))) > 0


def ring_faces(n_rings: int, n_around: int, outward: bool = True, skip_bands: tuple[int, ...] = ()) -> np.ndarray:
    """Triangles of pole 0 + n_rings rings + last pole; band b joins ring b and b+1 (0-based ring ids)."""
    s = np.arange(n_around)
    s1 = (s + 1) % n_around
    last = 1 + n_rings * n_around
    faces = [np.stack([np.zeros(n_around, int), 1 + s1, 1 + s], 1)]
    for b in range(n_rings - 1):
        if b in skip_bands:
            continue
        a0, a1 = 1 + b * n_around, 1 + (b + 1) * n_around
        faces += [np.stack([a0 + s, a0 + s1, a1 + s1], 1), np.stack([a0 + s, a1 + s1, a1 + s], 1)]
    a0 = 1 + (n_rings - 1) * n_around
    faces.append(np.stack([a0 + s, a0 + s1, np.full(n_around, last)], 1))
    faces = np.concatenate(faces)
    return faces if outward else faces[:, ::-1].copy()


def orthonormal_frame(axis: np.ndarray, hint: np.ndarray = np.array([0.0, 1.0, 0.0])) -> tuple[np.ndarray, ...]:
    """(side, front, axis) with `axis` normalised and `front` as close to `hint` as possible."""
    axis = axis / np.linalg.norm(axis)
    if abs(np.dot(axis, hint)) > 0.95:
        hint = np.array([0.0, 0.0, 1.0])
    front = hint - np.dot(hint, axis) * axis
    front /= np.linalg.norm(front)
    side = np.cross(front, axis)
    return side, front, axis


def capsule(
    p0: np.ndarray,
    p1: np.ndarray,
    r0: float,
    r1: float,
    n_around: int,
    n_cap: int,
    n_body: int,
    flatten: float = 1.0,
    hint: np.ndarray = np.array([0.0, 1.0, 0.0]),
    exponent: float = 2.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Tapered capsule from p0 to p1 with hemispherical ends; `flatten` scales the radius along `hint`."""
    side, front, axis = orthonormal_frame(p1 - p0, hint)
    length = np.linalg.norm(p1 - p0)
    cap = np.linspace(0.0, np.pi / 2, n_cap + 1)
    t_body = np.linspace(0.0, 1.0, n_body + 2)[1:-1]
    top = cap[::-1]  # the top cap runs from the body (angle pi/2) to the pole (angle 0)
    along = np.concatenate([-r0 * np.cos(cap), length * t_body, length + r1 * np.cos(top)])
    radius = np.concatenate([r0 * np.sin(cap), r0 + (r1 - r0) * t_body, r1 * np.sin(top)])
    centers = p0 + along[:, None] * axis
    return loft(centers, radius, radius * flatten, side, front, n_around, exponent)


def ellipsoid(
    center: np.ndarray, radii: np.ndarray, n_around: int, n_rings: int, axes: np.ndarray = np.eye(3)
) -> tuple[np.ndarray, np.ndarray]:
    """Ellipsoid with semi-axes radii along the rows of `axes` (side, front, pole axis)."""
    theta = np.linspace(0.0, np.pi, n_rings + 2)
    centers = center + (-np.cos(theta) * radii[2])[:, None] * axes[2]
    ring = np.sin(theta)
    return loft(centers, ring * radii[0], ring * radii[1], axes[0], axes[1], n_around)


def rigid_part(
    name: str, vertices: np.ndarray, faces: np.ndarray, joint: int, n_joints: int, rgb: tuple[float, float, float]
) -> Part:
    """A part skinned entirely to one joint with one colour."""
    weights = np.zeros((len(vertices), n_joints))
    weights[:, joint] = 1.0
    colours = np.tile(np.asarray(rgb, dtype=np.float64), (len(vertices), 1))
    return Part(name, vertices, faces, weights, colours)


def mirror_part(part: Part, joint_map: np.ndarray, name: str) -> Part:
    """Mirror a left part to the right (x -> -x): flips the winding and re-targets the weights' joints."""
    vertices = part.vertices * np.array([-1.0, 1.0, 1.0])
    weights = np.zeros_like(part.weights)
    weights[:, joint_map] = part.weights
    attributes = {k: v.copy() for k, v in part.attributes.items()}
    return Part(name, vertices, part.faces[:, ::-1].copy(), weights, part.colours.copy(), attributes)


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3 - 2 * t)
