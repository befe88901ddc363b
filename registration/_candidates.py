"""Candidate pairs for the similarity of a large collection: a cheap descriptor, k nearest.

All-pairs affine ICP is O(n^2) runs. Beyond a few dozen shapes the tree only needs, for
every shape, the pairs joining it to its nearest shapes (its similar shapes: the automatic
similarity rule looks at the 4 nearest) and the root's pairs (the first layer). A
descriptor that is invariant to what the affine ICP factors out (translation, scale,
rotation, reflection and, after whitening, any affine map) ranks the shapes; ICP then runs
on the ``k`` nearest by descriptor only: O(n k) runs. Ranking is O(n^2) descriptor
distances, computed in row blocks (O(n k) memory): 0.1 s at 2000 shapes, against minutes
of ICP.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = ["candidate_pairs", "shape_descriptor"]

RADIAL_BINS = 8
RADIUS_MAX = 3.0  # whitened radius covered by the bins (unit variance along each axis)
HARMONICS = 6
_BLOCK = 512


def shape_descriptor(normalised: FloatArray) -> FloatArray:
    """A pose-invariant descriptor of a shape: angular Fourier magnitudes per radial band.

    The points are whitened (centred, principal axes scaled to unit variance), which
    removes any affine map up to a rotation and a reflection. Each point falls into radial
    bands (linear weights between the two nearest band centres); for every band ``b`` and
    harmonic ``h = 0..HARMONICS``, ``|sum_p w_pb exp(i h theta_p)| / n``: harmonic 0 is the
    radial histogram, the others how the band's points spread around the centre; a
    magnitude does not change when the shape turns or mirrors.

    Returns
    -------
    ndarray, shape (RADIAL_BINS * (HARMONICS + 1),)
    """
    p = np.asarray(normalised, dtype=np.float64)
    c = p - p.mean(axis=0)
    cov = c.T @ c / max(len(c), 1)
    evals, evecs = np.linalg.eigh(cov)
    w = c @ evecs / np.sqrt(np.maximum(evals, 1e-12))
    r = np.hypot(w[:, 0], w[:, 1])
    theta = np.arctan2(w[:, 1], w[:, 0])
    # soft radial bands: band centres at (k + 0.5) * step
    step = RADIUS_MAX / RADIAL_BINS
    pos = np.clip(r / step - 0.5, 0.0, RADIAL_BINS - 1.0)
    lo = np.floor(pos).astype(np.intp)
    hi = np.minimum(lo + 1, RADIAL_BINS - 1)
    frac = pos - lo
    weights = np.zeros((len(p), RADIAL_BINS))
    rows = np.arange(len(p))
    weights[rows, lo] = 1.0 - frac
    weights[rows, hi] += frac  # each row once per statement: no repeated index
    phase = np.exp(1j * np.outer(theta, np.arange(HARMONICS + 1)))  # (n, H + 1)
    coeff = weights.T @ phase  # (bands, H + 1)
    return np.asarray(np.abs(coeff).ravel() / max(len(p), 1))


def candidate_pairs(normalised: Sequence[FloatArray], k: int) -> list[tuple[int, int]]:
    """Both directions of the pairs joining each shape to its `k` nearest by descriptor.

    Parameters
    ----------
    normalised : sequence of ndarray, shape (n_i, 2)
    k : int
        Nearest shapes per shape, at least 1 (fewer when the collection is smaller).

    Returns
    -------
    list of (int, int)
        Sorted (model, subject) pairs; at most ``2 n k``.
    """
    if k < 1:
        raise ValueError(f"k must be at least 1; got {k}")
    n = len(normalised)
    if n < 2:
        return []
    desc = np.stack([shape_descriptor(p) for p in normalised])
    kk = min(k, n - 1)
    sq = (desc**2).sum(axis=1)
    pairs: set[tuple[int, int]] = set()
    for start in range(0, n, _BLOCK):
        block = slice(start, min(start + _BLOCK, n))
        d2 = sq[block, None] + sq[None, :] - 2.0 * desc[block] @ desc.T
        d2[np.arange(d2.shape[0]), np.arange(block.start, block.stop)] = np.inf
        near = np.argpartition(d2, kk - 1, axis=1)[:, :kk]
        for i, row in zip(range(block.start, block.stop), near, strict=True):
            for j in row.tolist():
                pairs.add((i, j))
                pairs.add((j, i))
    return sorted(pairs)
