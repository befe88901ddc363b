"""The dynamic tree of Du et al. 2016 (section 3.3) and the baselines it is compared with.

All three methods register the root model to every other shape of a collection:

- :func:`build_dynamic_tree`: layer by layer, each waiting subject that is similar
  (affine-ICP distance D below the similarity threshold) to a tree member not yet tried
  for it is registered from that member: the root model *as already warped onto the
  member* is pre-aligned by affine ICP and warped by CPD onto the subject. The subject is
  accepted when e (eq. 10) is below the error threshold and the CPD displacement field
  does not fold the model; otherwise it waits for a later layer. Growth stops when every
  subject is attached or a layer adds nothing; what is left is reported unattached.
- :func:`build_static_tree`: the heuristic tree of Du et al. 2015: the same layered
  growth over the similarity graph, each subject attached to its most similar member of
  the previous layer, without any rejection; then CPD along the tree's edges.
- :func:`register_direct`: CPD from the root to every subject.

Direction of D: ``D[m, s]`` is computed with the member ``m`` as the moving model and the
subject ``s`` fixed, matching the direction of the registration that follows.
"""

from .._cpd import CPDOptions
from ._methods import build_dynamic_tree, build_static_tree, register_direct

__all__ = [
    "CPDOptions",
    "build_dynamic_tree",
    "build_static_tree",
    "register_direct",
]
