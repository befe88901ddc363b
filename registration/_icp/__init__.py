"""Affine ICP with bidirectional distance (Du et al. 2016, eqs. 2-9).

The algorithm alternates two steps until the distance stops decreasing:

1. correspondences both ways by nearest neighbour (eq. 3): ``c(i)`` is the subject point
   nearest to the transformed model point ``A x_i + t`` and ``d(j)`` the model point whose
   image is nearest to ``y_j``;
2. the closed-form least-squares affine map on the stacked pairs (eqs. 6-8).

It converges to a local minimum, so :func:`affine_icp` starts it from several poses: the
principal-axes ("whitening") alignment of the two shapes composed with rotations and
reflections, first on coarse subsamples of both shapes (all starts at once, vectorised),
then refines the best start on the full point sets with KD-trees.
"""

from ._affine import affine_icp
from ._fit import AffineICPResult, bidirectional_distance, fit_affine
from ._pairwise import PairPose, PreparedShape, pairwise_affine_icp, prepare_shape, rigid_turns

__all__ = [
    "AffineICPResult",
    "PairPose",
    "PreparedShape",
    "affine_icp",
    "bidirectional_distance",
    "fit_affine",
    "pairwise_affine_icp",
    "prepare_shape",
    "rigid_turns",
]

