"""The bidirectional registration error e of Du et al. 2016, eq. 10."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from ._points import as_points

__all__ = ["registration_error"]


def registration_error(q: ArrayLike, y: ArrayLike) -> float:
    """Bidirectional nearest-neighbour mean squared distance (eq. 10).

    .. math::

        e = \\Big(\\sum_{i=1}^N \\lVert q_i - y_{r(i)} \\rVert^2
              + \\sum_{j=1}^M \\lVert q_{s(j)} - y_j \\rVert^2\\Big) / (N + M)

    where :math:`r(i)` is the subject point nearest to :math:`q_i` and :math:`s(j)` the
    warped-model point nearest to :math:`y_j`.

    Parameters
    ----------
    q : array_like, shape (N, 2)
        The model after registration (warped model points).
    y : array_like, shape (M, 2)
        The subject.

    Returns
    -------
    float
        e, in squared units of the input coordinates (the tree reports it on
        size-normalised shapes).

    Raises
    ------
    ValueError
        If either input is not a finite (n, 2) array with at least one point.
    """
    qa = as_points(q, name="q", min_points=1)
    ya = as_points(y, name="y", min_points=1)
    forward, _ = cKDTree(ya).query(qa)
    backward, _ = cKDTree(qa).query(ya)
    total = float(np.dot(forward, forward) + np.dot(backward, backward))
    return total / (qa.shape[0] + ya.shape[0])
