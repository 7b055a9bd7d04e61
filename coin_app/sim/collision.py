"""2-D geometry kernels: oriented boxes, separating axes, rays and polygons (vectorized)."""

from __future__ import annotations

import numpy as np


def box_axes(heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit forward and left axes (N, 2) of boxes with the given headings."""
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([c, s], -1), np.stack([-s, c], -1)


def box_corners(center: np.ndarray, heading: np.ndarray, half_len: np.ndarray | float, half_wid: np.ndarray | float) -> np.ndarray:
    """Corners (N, 4, 2) of oriented boxes, counter-clockwise from front-left."""
    fwd, left = box_axes(heading)
    hl = np.broadcast_to(np.asarray(half_len, dtype=float), heading.shape)[:, None]
    hw = np.broadcast_to(np.asarray(half_wid, dtype=float), heading.shape)[:, None]
    f, lft = fwd * hl, left * hw
    return np.stack([center + f + lft, center - f + lft, center - f - lft, center + f - lft], axis=1)


def boxes_overlap(
    c1: np.ndarray,
    h1: np.ndarray,
    half1: np.ndarray,
    c2: np.ndarray,
    h2: np.ndarray,
    half2: np.ndarray,
) -> np.ndarray:
    """Whether pairs of oriented boxes overlap (separating-axis test); inputs row-aligned.

    ``half1``/``half2`` are (N, 2) half extents (along, across) of each box.
    """
    # in box 1's frame box 1 is axis-aligned; box 2 is rotated by dh = h2 - h1
    c, s = np.cos(h1), np.sin(h1)
    dx, dy = c2[:, 0] - c1[:, 0], c2[:, 1] - c1[:, 1]
    tx, ty = c * dx + s * dy, -s * dx + c * dy
    dh = h2 - h1
    cos_dh, sin_dh = np.cos(dh), np.sin(dh)
    cd, sd = np.abs(cos_dh), np.abs(sin_dh)
    a1, b1, a2, b2 = half1[:, 0], half1[:, 1], half2[:, 0], half2[:, 1]
    overlap = np.abs(tx) <= a1 + a2 * cd + b2 * sd  # box 1's forward axis
    overlap &= np.abs(ty) <= b1 + a2 * sd + b2 * cd  # box 1's left axis
    # box 2's axes: project the centre offset and box 1 onto them
    u = cos_dh * tx + sin_dh * ty
    w = -sin_dh * tx + cos_dh * ty
    overlap &= np.abs(u) <= a2 + a1 * cd + b1 * sd
    overlap &= np.abs(w) <= b2 + a1 * sd + b1 * cd
    return overlap


def ray_box_distance(
    origin: np.ndarray,
    direction: np.ndarray,
    center: np.ndarray,
    heading: np.ndarray,
    half: np.ndarray,
) -> np.ndarray:
    """Distance along unit rays to oriented boxes (slab method); inf where the ray misses.

    A ray starting inside its box returns 0. All inputs are row-aligned (N, ...).
    """
    fwd, left = box_axes(heading)
    rel = origin - center
    o = np.stack([np.einsum("nd,nd->n", rel, fwd), np.einsum("nd,nd->n", rel, left)], 1)
    v = np.stack([np.einsum("nd,nd->n", direction, fwd), np.einsum("nd,nd->n", direction, left)], 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / v
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
    # a ray parallel to a slab: inside it -> (-inf, inf), outside -> empty
    parallel = v == 0
    inside = np.abs(o) <= half
    lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    t_enter = lo.max(1)
    t_exit = hi.min(1)
    hit = (t_exit >= np.maximum(t_enter, 0.0)) & np.isfinite(t_exit)
    return np.where(hit, np.maximum(t_enter, 0.0), np.inf)


def footprint_samples(center: np.ndarray, heading: np.ndarray, half_len: float, half_wid: float) -> np.ndarray:
    """Nine points (N, 9, 2) on a box footprint: centre, corners and edge midpoints."""
    fwd, left = box_axes(heading)
    coefs = np.array([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=float)
    return center[:, None, :] + coefs[None, :, 0:1] * half_len * fwd[:, None, :] + coefs[None, :, 1:2] * half_wid * left[:, None, :]


def box_circle_overlap(center: np.ndarray, heading: np.ndarray, half: np.ndarray, circle: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Whether oriented boxes overlap circles (row-aligned): the circle centre's distance to the box is <= its radius.

    ``half`` is (N, 2) half extents (along, across); ``circle`` (N, 2) centres; ``radius`` (N,).
    """
    c, s = np.cos(heading), np.sin(heading)
    dx, dy = circle[:, 0] - center[:, 0], circle[:, 1] - center[:, 1]
    u, w = c * dx + s * dy, -s * dx + c * dy  # circle centre in the box frame
    ex = np.maximum(np.abs(u) - half[:, 0], 0.0)
    ey = np.maximum(np.abs(w) - half[:, 1], 0.0)
    return ex**2 + ey**2 <= np.asarray(radius) ** 2
