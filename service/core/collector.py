"""The cyclic garbage collector's first threshold in the service's own processes.

A full result is millions of small containers (the 73 full-resolution 永 glyphs: 26.6 MB of
JSON, about five million lists and floats), built by a worker from the library's result and
parsed again by the server for every ``?full=true`` read. With CPython's default threshold
(700 allocations between young collections) each such document is walked by the collector
several times while it grows. Measured on that result (``bench/RESULTS.md`` 7.19):

* the worker's document (``json_safe`` and the API document, after the library's
  ``to_dict``, which pauses the collector itself): 0.21-0.22 s with 700, 0.12-0.15 s with
  10 000; in one process with a full collection after each, the whole path from
  ``to_dict`` to orjson took 1.4-1.8 s with 700 and 0.72-0.81 s with 10 000 (no pause);
* the server's ``GET /v1/jobs/{id}/result?full=true`` (orjson per subject, the shared
  steps expanded, pydantic's validation and JSON; 54 MB), timed at the client: 1.71-2.28 s
  with 700, 1.24-1.72 s with 10 000 (six reads each).

The documents hold no reference cycles, so collecting less often frees nothing later than
it would have been; the collector still runs, on 10 000 allocations instead of 700.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

#: The first threshold set in the API server's and the workers' processes.
SERVICE_GC_THRESHOLD = 10_000


def tune_collector() -> None:
    """Raise this process's first collector threshold to :data:`SERVICE_GC_THRESHOLD`
    (a higher one already set is kept); the older generations' thresholds are kept."""
    first, second, third = gc.get_threshold()
    gc.set_threshold(max(first, SERVICE_GC_THRESHOLD), second, third)


@contextmanager
def paused() -> Iterator[None]:
    """The collector off while a large document without reference cycles is parsed or
    built (then back as it was): for the client's reads of full results, in processes
    whose threshold is the default (the library's ``CollectionResult.to_dict`` pauses it
    the same way)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()
