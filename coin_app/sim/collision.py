"""2-D geometry kernels: oriented boxes, separating axes, rays and polygons.

The separating-axis test and the footprint samples are compiled scalar rules (``_box_overlap``,
``_footprint_point``); the array functions and the simulator's road and crash kernels call them.
"""

from __future__ import annotations

import numba
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


@numba.njit(cache=True, error_model="numpy")
def _box_overlap(x1: float, y1: float, h1: float, a1: float, b1: float, x2: float, y2: float, h2: float, a2: float, b2: float) -> bool:
    """Whether two oriented boxes overlap (separating axes): centres, headings and half extents (along, across)."""
    # in box 1's frame box 1 is axis-aligned; box 2 is rotated by dh = h2 - h1
    c, s = np.cos(h1), np.sin(h1)
    dx, dy = x2 - x1, y2 - y1
    tx, ty = c * dx + s * dy, -s * dx + c * dy
    dh = h2 - h1
    cos_dh, sin_dh = np.cos(dh), np.sin(dh)
    cd, sd = abs(cos_dh), abs(sin_dh)
    if not abs(tx) <= a1 + a2 * cd + b2 * sd:  # box 1's forward axis
        return False
    if not abs(ty) <= b1 + a2 * sd + b2 * cd:  # box 1's left axis
        return False
    # box 2's axes: project the centre offset and box 1 onto them
    u = cos_dh * tx + sin_dh * ty
    w = -sin_dh * tx + cos_dh * ty
    return abs(u) <= a2 + a1 * cd + b1 * sd and abs(w) <= b2 + a1 * sd + b1 * cd


@numba.njit(cache=True)
def _boxes_overlap(c1: np.ndarray, h1: np.ndarray, half1: np.ndarray, c2: np.ndarray, h2: np.ndarray, half2: np.ndarray) -> np.ndarray:
    out = np.empty(len(h1), np.bool_)
    for i in range(len(h1)):
        out[i] = _box_overlap(c1[i, 0], c1[i, 1], h1[i], half1[i, 0], half1[i, 1], c2[i, 0], c2[i, 1], h2[i], half2[i, 0], half2[i, 1])
    return out


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
    n = len(np.atleast_1d(h1))
    f = np.float64
    return _boxes_overlap(
        *(np.ascontiguousarray(np.broadcast_to(np.asarray(a, f), shape)) for a, shape in ((c1, (n, 2)), (h1, (n,)), (half1, (n, 2)))),
        *(np.ascontiguousarray(np.broadcast_to(np.asarray(a, f), shape)) for a, shape in ((c2, (n, 2)), (h2, (n,)), (half2, (n, 2)))),
    )


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


FOOTPRINT_COEFS = np.array([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=float)


@numba.njit(cache=True)
def _footprint_point(x: float, y: float, c: float, s: float, half_len: float, half_wid: float, k: int) -> tuple[float, float]:
    """Footprint sample ``k`` (``FOOTPRINT_COEFS``) of a box at (x, y) with forward axis (c, s)."""
    a, b = FOOTPRINT_COEFS[k, 0] * half_len, FOOTPRINT_COEFS[k, 1] * half_wid
    return x + a * c + b * -s, y + a * s + b * c


@numba.njit(cache=True)
def _footprint_samples(center: np.ndarray, heading: np.ndarray, half_len: float, half_wid: float) -> np.ndarray:
    out = np.empty((len(heading), 9, 2))
    for i in range(len(heading)):
        c, s = np.cos(heading[i]), np.sin(heading[i])
        for k in range(9):
            out[i, k, 0], out[i, k, 1] = _footprint_point(center[i, 0], center[i, 1], c, s, half_len, half_wid, k)
    return out


def footprint_samples(center: np.ndarray, heading: np.ndarray, half_len: float, half_wid: float) -> np.ndarray:
    """Nine points (N, 9, 2) on a box footprint: centre, corners and edge midpoints."""
    f = np.float64
    return _footprint_samples(np.ascontiguousarray(center, f), np.ascontiguousarray(heading, f), float(half_len), float(half_wid))


@numba.njit(cache=True)
def _grid_row(table: np.ndarray, origin: np.ndarray, cell: float, shape: np.ndarray, x: float, y: float) -> np.ndarray:
    """The row of ``GridIndex.table`` of the cell of (x, y) (clamped to the grid): the items near it, -1 padded."""
    cx = min(max(int(np.floor((x - origin[0]) / cell)), 0), shape[0] - 1)
    cy = min(max(int(np.floor((y - origin[1]) / cell)), 0), shape[1] - 1)
    return table[cx * shape[1] + cy]


@numba.njit(cache=True, error_model="numpy")
def touches_boxes(
    pos: np.ndarray,
    heading: np.ndarray,
    half: np.ndarray,
    table: np.ndarray,
    origin: np.ndarray,
    cell: float,
    shape: np.ndarray,
    box_center: np.ndarray,
    box_heading: np.ndarray,
    box_half: np.ndarray,
) -> np.ndarray:
    """(N,) whether each footprint (``half`` extents) overlaps one of the boxes listed near it in the grid (``GridIndex``).

    A box whose bounding circle cannot reach the footprint's is skipped before the separating-axis test.
    """
    out = np.zeros(len(heading), np.bool_)
    half_diag = np.hypot(half[0], half[1])
    for i in range(len(heading)):
        x, y = pos[i, 0], pos[i, 1]
        for j in _grid_row(table, origin, cell, shape, x, y):
            if j < 0:
                break
            rx, ry = x - box_center[j, 0], y - box_center[j, 1]
            if not rx**2 + ry**2 < (box_half[j, 0] + half_diag + box_half[j, 1]) ** 2:
                continue
            bx, by, bh, ba, bb = box_center[j, 0], box_center[j, 1], box_heading[j], box_half[j, 0], box_half[j, 1]
            if _box_overlap(x, y, heading[i], half[0], half[1], bx, by, bh, ba, bb):
                out[i] = True
                break
    return out


@numba.njit(cache=True, error_model="numpy")
def footprint_in_polygons(
    pos: np.ndarray,
    heading: np.ndarray,
    half: np.ndarray,
    table: np.ndarray,
    origin: np.ndarray,
    cell: float,
    shape: np.ndarray,
    centroid: np.ndarray,
    radius: np.ndarray,
    normals: np.ndarray,
    offsets: np.ndarray,
) -> np.ndarray:
    """(N,) whether a footprint sample point (``footprint_samples``) lies in one of the convex polygons listed near it in the
    grid (half-planes ``normals . p <= offsets``; a polygon farther than its ``radius`` + the footprint's is skipped)."""
    out = np.zeros(len(heading), np.bool_)
    half_diag = np.hypot(half[0], half[1])
    for i in range(len(heading)):
        x, y = pos[i, 0], pos[i, 1]
        c, s = np.cos(heading[i]), np.sin(heading[i])
        for j in _grid_row(table, origin, cell, shape, x, y):
            if j < 0:
                break
            if not np.hypot(x - centroid[j, 0], y - centroid[j, 1]) < radius[j] + half_diag:
                continue
            for k in range(9):
                px, py = _footprint_point(x, y, c, s, half[0], half[1], k)
                inside = True
                for e in range(normals.shape[1]):
                    if not normals[j, e, 0] * px + normals[j, e, 1] * py <= offsets[j, e]:
                        inside = False
                        break
                if inside:
                    out[i] = True
                    break
            if out[i]:
                break
    return out


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


@numba.njit(cache=True, error_model="numpy")
def same_env_overlaps(poses: np.ndarray, live: np.ndarray, slots_per_env: int, half: np.ndarray, max_dist: float) -> np.ndarray:
    """(N,) whether each live slot's box (``half`` extents) overlaps another live box of its env (slots ``e S .. e S + S - 1``)
    at one of the instants of ``poses`` (N, K, 3): x, y and heading of every slot at each of K instants.

    Only pairs with centres closer than ``max_dist`` at that instant are tested.
    """
    n, instants = poses.shape[0], poses.shape[1]
    out = np.zeros(n, np.bool_)
    for base in range(0, n, slots_per_env):
        for i in range(base, base + slots_per_env):
            if not live[i]:
                continue
            for j in range(i + 1, base + slots_per_env):
                if not live[j]:
                    continue
                for k in range(instants):
                    a, b = poses[i, k], poses[j, k]
                    dx, dy = a[0] - b[0], a[1] - b[1]
                    if dx * dx + dy * dy < max_dist**2 and _box_overlap(
                        a[0], a[1], a[2], half[0], half[1], b[0], b[1], b[2], half[0], half[1]
                    ):
                        out[i] = True
                        out[j] = True
                        break
    return out


@numba.njit(cache=True, error_model="numpy")
def places_blocked(
    place_pos: np.ndarray,
    place_heading: np.ndarray,
    place_half: np.ndarray,
    pos: np.ndarray,
    heading: np.ndarray,
    half: np.ndarray,
    live: np.ndarray,
    envs: np.ndarray,
    slots_per_env: int,
) -> np.ndarray:
    """(E, P) whether place p's box (``place_half`` extents) overlaps a live vehicle's box of env e, for the envs flagged in
    ``envs`` (E,) (False elsewhere)."""
    out = np.zeros((len(envs), len(place_heading)), np.bool_)
    for e in range(len(envs)):
        if not envs[e]:
            continue
        for j in range(e * slots_per_env, (e + 1) * slots_per_env):
            if not live[j]:
                continue
            for p in range(len(place_heading)):
                if not out[e, p] and _box_overlap(
                    place_pos[p, 0], place_pos[p, 1], place_heading[p], place_half[0], place_half[1],
                    pos[j, 0], pos[j, 1], heading[j], half[0], half[1],
                ):  # fmt: skip
                    out[e, p] = True
    return out
