"""t-SNE and k-means for the latent-space figure (COIN App. B.1), through scikit-learn.

:func:`tsne` is scikit-learn's Barnes-Hut ``TSNE`` (PCA initialization, automatic learning
rate); :func:`kmeans` is scikit-learn's ``KMeans`` (k-means++, 10 starts). Both run on one
thread (the project's thread discipline) and are deterministic for a given ``seed``. They
replaced hand-written versions: ``benchmarks/embedding.py`` measures both side by side
(docs/reliability.md quotes the figures).
"""

from __future__ import annotations

import numpy as np
from sklearn.cluster import KMeans
from sklearn.manifold import TSNE
from threadpoolctl import threadpool_limits


def tsne(x: np.ndarray, dim: int = 2, perplexity: float = 30.0, iterations: int = 1000, seed: int = 0) -> np.ndarray:
    """A (n, dim) t-SNE embedding of the rows of ``x``."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    if x.ndim != 2 or n < 3:
        raise ValueError(f"t-SNE needs a 2-D array of at least 3 rows; got shape {x.shape}")
    if not 1.0 <= perplexity < n:
        raise ValueError(f"bad perplexity {perplexity}; allowed: 1 <= perplexity < number of points ({n})")
    if iterations < 250:
        raise ValueError(f"bad iterations {iterations}; allowed: an integer >= 250")
    method = "barnes_hut" if dim <= 3 else "exact"  # Barnes-Hut is defined for 2-D and 3-D embeddings only
    with threadpool_limits(limits=1):
        model = TSNE(dim, perplexity=perplexity, max_iter=iterations, init="pca", method=method, random_state=seed, n_jobs=1)
        return model.fit_transform(x)


def kmeans(x: np.ndarray, k: int, seed: int = 0, iters: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """(labels (n,), centers (k, d)) of k-means on the rows of ``x``."""
    x = np.asarray(x, dtype=float)
    if not 1 <= k <= len(x):
        raise ValueError(f"bad k {k}; allowed: 1 <= k <= number of points ({len(x)})")
    with threadpool_limits(limits=1):
        model = KMeans(k, n_init=10, max_iter=iters, random_state=seed).fit(x)
    return model.labels_, model.cluster_centers_
