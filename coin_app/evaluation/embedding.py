"""Small, dependency-free t-SNE and k-means for the latent-space figure (COIN App. B.1).

:func:`tsne` is exact t-SNE (van der Maaten & Hinton 2008): Gaussian affinities calibrated to
a perplexity by a vectorized bisection per point, symmetrized; a Student-t embedding fitted by
gradient descent with momentum, per-coordinate gains and early exaggeration. It is O(n^2) in
memory and time, meant for the few thousand latent samples of the figure (2,000 points: ~30 MB,
well under a minute of CPU time). :func:`kmeans` is Lloyd's algorithm with k-means++ seeding. Both are
deterministic for a given ``seed``.
"""

from __future__ import annotations

import numpy as np


def _sq_distances(x: np.ndarray) -> np.ndarray:
    """Pairwise squared Euclidean distances (n, n), clipped at 0."""
    sq = (x * x).sum(1)
    return np.maximum(sq[:, None] + sq[None, :] - 2.0 * x @ x.T, 0.0)


def conditional_affinities(x: np.ndarray, perplexity: float, tol: float = 1e-5, iters: int = 100) -> np.ndarray:
    """Row-stochastic p(j | i) (n, n), zero diagonal, each row's perplexity exp(entropy) equal to ``perplexity``."""
    n = len(x)
    d2 = _sq_distances(np.asarray(x, dtype=float))
    scale = np.median(d2[~np.eye(n, dtype=bool)]) if n > 1 else 1.0
    d2 = d2 / (scale if scale > 0 else 1.0)
    np.fill_diagonal(d2, np.inf)
    target = np.log(perplexity)
    beta, lo, hi = np.ones(n), np.zeros(n), np.full(n, np.inf)
    finite = np.where(np.isinf(d2), 0.0, d2)
    for _ in range(iters):
        p = np.exp(-(d2 - np.min(d2, axis=1, keepdims=True)) * beta[:, None])
        s = p.sum(1)
        entropy = np.log(s) + beta * ((finite - np.min(d2, axis=1, keepdims=True)) * p).sum(1) / s
        diff = entropy - target
        if np.all(np.abs(diff) < tol):
            break
        up = diff > 0  # too flat: sharpen
        lo = np.where(up, beta, lo)
        hi = np.where(up, hi, beta)
        beta = np.where(np.isinf(hi), beta * 2.0, (lo + hi) / 2.0)
    return p / p.sum(1, keepdims=True)


def affinities(x: np.ndarray, perplexity: float) -> np.ndarray:
    """Symmetric joint probabilities P (n, n), summing to 1, from the conditional affinities."""
    p = conditional_affinities(x, perplexity)
    joint = (p + p.T) / (2.0 * len(p))
    return np.maximum(joint, 1e-12)


def tsne(
    x: np.ndarray,
    dim: int = 2,
    perplexity: float = 30.0,
    iterations: int = 750,
    seed: int = 0,
    exaggeration: float = 12.0,
    exaggeration_iters: int = 250,
) -> np.ndarray:
    """A (n, dim) t-SNE embedding of the rows of ``x``."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    if x.ndim != 2 or n < 3:
        raise ValueError(f"t-SNE needs a 2-D array of at least 3 rows; got shape {x.shape}")
    if not 1.0 <= perplexity < n:
        raise ValueError(f"bad perplexity {perplexity}; allowed: 1 <= perplexity < number of points ({n})")
    p = affinities(x, perplexity)
    rng = np.random.default_rng(seed)
    y = rng.normal(0.0, 1e-4, size=(n, dim))
    update = np.zeros_like(y)
    gains = np.ones_like(y)
    lr = max(n / exaggeration / 4.0, 50.0)
    for it in range(iterations):
        num = 1.0 / (1.0 + _sq_distances(y))
        np.fill_diagonal(num, 0.0)
        q = np.maximum(num / num.sum(), 1e-12)
        pq = ((p * exaggeration if it < exaggeration_iters else p) - q) * num
        grad = 4.0 * (pq.sum(1)[:, None] * y - pq @ y)
        same = (grad > 0) == (update > 0)
        gains = np.maximum(np.where(same, gains * 0.8, gains + 0.2), 0.01)
        update = (0.5 if it < exaggeration_iters else 0.8) * update - lr * gains * grad
        y = y + update
        y = y - y.mean(0)
    return y


def kmeans(x: np.ndarray, k: int, seed: int = 0, iters: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """(labels (n,), centers (k, d)) of Lloyd's k-means with k-means++ seeding."""
    x = np.asarray(x, dtype=float)
    if not 1 <= k <= len(x):
        raise ValueError(f"bad k {k}; allowed: 1 <= k <= number of points ({len(x)})")
    rng = np.random.default_rng(seed)
    centers = [x[rng.integers(len(x))]]
    for _ in range(1, k):
        d2 = np.min(((x[:, None, :] - np.array(centers)[None]) ** 2).sum(-1), axis=1)
        total = d2.sum()
        centers.append(x[rng.choice(len(x), p=d2 / total)] if total > 0 else x[rng.integers(len(x))])
    c = np.array(centers)
    labels = np.full(len(x), -1)
    for _ in range(iters):
        new = np.argmin(((x[:, None, :] - c[None]) ** 2).sum(-1), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        for j in range(k):
            members = x[labels == j]
            if len(members):
                c[j] = members.mean(0)
    return labels, c
