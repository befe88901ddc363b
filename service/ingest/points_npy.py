"""NPY uploads: a numeric ``(n, 2)`` array written by ``numpy.save``, loaded without pickle."""

from __future__ import annotations

import io

import numpy as np

from service.ingest import _base
from service.ingest._base import DEFAULT_LIMITS, FloatArray, IngestError, Limits


def points_from_npy(
    data: bytes,
    *,
    limits: Limits = DEFAULT_LIMITS,
) -> FloatArray:
    """Points from an ``.npy`` file: a numeric (integer or float) ``(n, 2)`` array.

    The header is checked before any data is read, so a header declaring a huge shape cannot
    make the loader allocate memory; the data is then read with ``allow_pickle=False``, so
    object arrays (which would need unpickling, i.e. running code) are refused.
    """
    if not data:
        raise IngestError("empty file")
    fp = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, _fortran, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, _fortran, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            raise IngestError(
                f"unsupported npy format version {version[0]}.{version[1]}; "
                f"save a plain numeric array with numpy.save"
            )
    except IngestError:
        raise
    except (ValueError, SyntaxError, EOFError, TypeError) as e:
        raise IngestError(f"not a valid npy file: {e}") from e
    if dtype.hasobject:
        raise IngestError(
            "the npy file holds Python objects (pickled data), which are refused for safety; "
            "save a numeric array, e.g. numpy.save(f, points.astype(float))"
        )
    if dtype.fields is not None or dtype.kind not in "iuf":
        raise IngestError(f"expected numeric coordinates (integers or floats); got dtype {dtype}")
    if len(shape) != 2 or shape[1] != 2:
        raise IngestError(f"expected points of shape (n, 2); got shape {tuple(shape)}")
    _base.check_count(int(shape[0]), limits)
    try:
        arr = np.load(io.BytesIO(data), allow_pickle=False)
    except ValueError as e:
        raise IngestError(f"could not read the npy file: {e}") from e
    except (OSError, EOFError) as e:
        raise IngestError(f"could not read the npy file: {e}") from e
    if not isinstance(arr, np.ndarray):  # pragma: no cover - magic already checked
        raise IngestError("not a valid npy file")
    return _base.finalise(arr, limits)
