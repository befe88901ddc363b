"""Pictures of a registration job, from its result document to PNG/SVG bytes.

Pure functions: they take the JSON of ``GET /v1/jobs/{id}/result`` (and, for a subject, that
subject's entry and its points) and return a :class:`Rendered` (``data`` bytes,
``media_type``, pixel ``width`` / ``height``, and ``meta`` describing what was drawn).
They use matplotlib's Agg and SVG renderers without ``pyplot`` and serialise rendering on one
lock, so they are safe in a web server's thread pool.

* :func:`render_tree` — the tree by layer, edges coloured by e, unattached shapes apart;
* :func:`render_subject` — a subject with the warped model and correspondence lines, beside
  direct CPD's result when the job compared with it;
* :func:`render_summary` — e per layer (mean and 95th percentile), tree against direct CPD.
"""

from service.plots._common import MEDIA_TYPES, Rendered
from service.plots._doc import find_subject, layer_statistics
from service.plots.subject import render_subject
from service.plots.summary import render_summary
from service.plots.tree import render_tree

__all__ = [
    "MEDIA_TYPES",
    "Rendered",
    "find_subject",
    "layer_statistics",
    "render_subject",
    "render_summary",
    "render_tree",
]
