"""coin_app's former hand-written t-SNE and k-means against scikit-learn's, on the latent figure's sizes.

Usage: python benchmarks/embedding.py [--points 500 1500 3000] [--dim 16] [--clusters 6] [--repeats 1]

Data: ``--clusters`` Gaussian blobs in ``--dim`` dimensions with unequal spreads (what the CVAE
latents of the COIN App. B.1 figure look like: a few behaviour modes), seeded. For each size it
prints, side by side in one run, one BLAS thread each:
- t-SNE (perplexity 30): wall time and trustworthiness at 10 neighbours (van der Maaten 2009; 1 is
  perfect) of the hand-written exact t-SNE, kept here as the reference, and of scikit-learn's
  Barnes-Hut ``TSNE`` (PCA init), which ``coin_app.evaluation.embedding`` now uses;
- k-means (k = ``--clusters``): wall time, inertia and the adjusted Rand index against the true
  blobs, for the hand-written Lloyd + k-means++ (one start) and scikit-learn's ``KMeans``
  (10 starts, the report's setting).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from functools import partial

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from sklearn.manifold import TSNE, trustworthiness  # noqa: E402
from sklearn.metrics import adjusted_rand_score  # noqa: E402

from coin_app.evaluation.embedding import kmeans, tsne  # noqa: E402


def handwritten_tsne(x: np.ndarray, perplexity: float = 30.0, seed: int = 0, iterations: int = 750) -> np.ndarray:
    """The exact t-SNE coin_app shipped before scikit-learn's (gradient descent with gains, early exaggeration)."""
    n = len(x)
    sq = (x * x).sum(1)
    d2 = np.maximum(sq[:, None] + sq[None, :] - 2.0 * x @ x.T, 0.0)
    d2 = d2 / np.median(d2[~np.eye(n, dtype=bool)])
    np.fill_diagonal(d2, np.inf)
    target, beta, lo, hi = np.log(perplexity), np.ones(n), np.zeros(n), np.full(n, np.inf)
    finite, dmin = np.where(np.isinf(d2), 0.0, d2), d2.min(1, keepdims=True)
    for _ in range(100):
        p = np.exp(-(d2 - dmin) * beta[:, None])
        s = p.sum(1)
        diff = np.log(s) + beta * ((finite - dmin) * p).sum(1) / s - target
        if np.all(np.abs(diff) < 1e-5):
            break
        up = diff > 0
        lo, hi = np.where(up, beta, lo), np.where(up, hi, beta)
        beta = np.where(np.isinf(hi), beta * 2.0, (lo + hi) / 2.0)
    p = p / p.sum(1, keepdims=True)
    p = np.maximum((p + p.T) / (2.0 * n), 1e-12)
    rng = np.random.default_rng(seed)
    y, update, gains = rng.normal(0.0, 1e-4, size=(n, 2)), np.zeros((n, 2)), np.ones((n, 2))
    lr = max(n / 12.0 / 4.0, 50.0)
    for it in range(iterations):
        yy = (y * y).sum(1)
        num = 1.0 / (1.0 + np.maximum(yy[:, None] + yy[None, :] - 2.0 * y @ y.T, 0.0))
        np.fill_diagonal(num, 0.0)
        q = np.maximum(num / num.sum(), 1e-12)
        pq = ((p * 12.0 if it < 250 else p) - q) * num
        grad = 4.0 * (pq.sum(1)[:, None] * y - pq @ y)
        gains = np.maximum(np.where((grad > 0) == (update > 0), gains * 0.8, gains + 0.2), 0.01)
        update = (0.5 if it < 250 else 0.8) * update - lr * gains * grad
        y = y + update - (y + update).mean(0)
    return y


def handwritten_kmeans(x: np.ndarray, k: int, seed: int = 0, iters: int = 100) -> np.ndarray:
    """Lloyd's algorithm with one k-means++ start, as coin_app shipped it; returns the labels."""
    rng = np.random.default_rng(seed)
    centers = [x[rng.integers(len(x))]]
    for _ in range(1, k):
        d2 = np.min(((x[:, None, :] - np.array(centers)[None]) ** 2).sum(-1), axis=1)
        centers.append(x[rng.choice(len(x), p=d2 / d2.sum())])
    c, labels = np.array(centers), np.full(len(x), -1)
    for _ in range(iters):
        new = np.argmin(((x[:, None, :] - c[None]) ** 2).sum(-1), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        for j in range(k):
            if np.any(labels == j):
                c[j] = x[labels == j].mean(0)
    return labels


def blobs(n: int, dim: int, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points from ``k`` Gaussian blobs of unequal spread in ``dim`` dimensions, and their blob labels."""
    rng = np.random.default_rng(seed)
    centers = rng.normal(0.0, 3.0, size=(k, dim))
    spreads = rng.uniform(0.5, 2.0, size=k)
    truth = rng.integers(k, size=n)
    return centers[truth] + rng.normal(size=(n, dim)) * spreads[truth, None], truth


def inertia(x: np.ndarray, labels: np.ndarray) -> float:
    """Sum of squared distances of the points to their cluster's mean."""
    return float(sum(((x[labels == j] - x[labels == j].mean(0)) ** 2).sum() for j in np.unique(labels)))


def timed(fn: Callable[[], np.ndarray]) -> tuple[np.ndarray, float]:
    """(result, seconds) of one call."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main() -> None:
    """Print the side-by-side table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, nargs="+", default=[500, 1500, 3000])
    ap.add_argument("--dim", type=int, default=16)
    ap.add_argument("--clusters", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    k, seed = args.clusters, args.seed
    print(f"{'points':>6}  {'method':<32} {'seconds':>8}  {'quality':>26}")
    for n in args.points:
        x, truth = blobs(n, args.dim, k, seed)
        embeddings = {
            "t-SNE hand-written (exact)": partial(handwritten_tsne, x, seed=seed),
            "t-SNE scikit-learn (coin_app)": partial(tsne, x, seed=seed),
            "t-SNE scikit-learn exact": partial(TSNE(2, perplexity=30.0, method="exact", init="pca", random_state=seed).fit_transform, x),
        }
        for label, fn in embeddings.items():
            y, s = timed(fn)
            print(f"{n:>6}  {label:<32} {s:8.2f}  trustworthiness@10 {trustworthiness(x, y, n_neighbors=10):.4f}", flush=True)
        clusterings = {
            "k-means hand-written (1 start)": partial(handwritten_kmeans, x, k, seed),
            "k-means scikit-learn (coin_app)": lambda x=x: kmeans(x, k, seed=seed)[0],
        }
        for label, fn in clusterings.items():
            lab, s = timed(fn)
            quality = f"inertia {inertia(x, lab):10.1f}  ARI {adjusted_rand_score(truth, lab):.3f}"
            print(f"{n:>6}  {label:<32} {s:8.2f}  {quality}", flush=True)
    print("summary: higher trustworthiness and ARI, lower inertia and seconds are better (one BLAS thread each)")


if __name__ == "__main__":
    main()
