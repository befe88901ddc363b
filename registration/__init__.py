"""regtree.registration: non-rigid registration of 2D shape collections.

A pure numpy/scipy implementation of Du et al. 2016, "Robust non-rigid point set
registration via building tree dynamically": affine ICP with bidirectional distance
(eqs. 2-9) as the similarity, CPD non-rigid registration (Myronenko & Song 2010), the
registration error of eq. 10, the dynamic tree of section 3.3, and the baselines it is
compared against (direct CPD and the static tree).

Typical use::

    from registration import build_dynamic_tree
    result = build_dynamic_tree(shapes, root=0, compare_direct=True)
    result.summary()["layer_ge_3"]      # mean and 95th percentile of e, as in the paper
    result.transform_for(5).apply(pts)  # root-model points mapped onto subject 5
"""

from ._cpd import (
    CPDOptions,
    CPDResult,
    NonrigidTransform,
    compiled_kernel,
    compiled_simd,
    cpd_nonrigid,
)
from ._dask import DaskClusterError, DaskExecutor
from ._error import registration_error
from ._executor import (
    Executor,
    LocalProcessExecutor,
    SerialExecutor,
    WorkerProcessDied,
    default_executor,
    start_fork_server,
)
from ._grouping import (
    GroupingResult,
    InstanceComparison,
    MouldGroup,
    compare_instances,
    group_instances,
)
from ._icp import AffineICPResult, affine_icp, bidirectional_distance, fit_affine
from ._pointmap import jacobian_determinants
from ._points import Normalization, as_points, normalise, resample
from ._result import Attempt, CollectionResult, SubjectResult, error_statistics
from ._similarity import ProgressCallback, Similarity, similarity_matrix
from ._transform import AffineTransform, ChainTransform, expand_shared_steps
from ._tree import build_dynamic_tree, build_static_tree, register_direct

__all__ = [
    "AffineICPResult",
    "AffineTransform",
    "Attempt",
    "CPDOptions",
    "CPDResult",
    "ChainTransform",
    "CollectionResult",
    "DaskClusterError",
    "DaskExecutor",
    "Executor",
    "GroupingResult",
    "InstanceComparison",
    "LocalProcessExecutor",
    "MouldGroup",
    "NonrigidTransform",
    "Normalization",
    "ProgressCallback",
    "SerialExecutor",
    "Similarity",
    "SubjectResult",
    "WorkerProcessDied",
    "affine_icp",
    "as_points",
    "bidirectional_distance",
    "build_dynamic_tree",
    "build_static_tree",
    "compare_instances",
    "compiled_kernel",
    "compiled_simd",
    "cpd_nonrigid",
    "default_executor",
    "error_statistics",
    "expand_shared_steps",
    "fit_affine",
    "group_instances",
    "jacobian_determinants",
    "normalise",
    "register_direct",
    "registration_error",
    "resample",
    "similarity_matrix",
    "start_fork_server",
]
