"""Shape files on disk: which ones an upload sends, and points as JSON lists."""

from __future__ import annotations

import fnmatch
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

#: Point files, and images, that :meth:`RegtreeClient.upload_folder` sends (by suffix).
POINT_SUFFIXES: dict[str, str] = {
    ".txt": "text/plain",
    ".csv": "text/csv",
    ".json": "application/json",
    ".npy": "application/octet-stream",
}
UPLOAD_SUFFIXES: dict[str, str] = {
    **POINT_SUFFIXES,
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
}


def _points_list(points: ArrayLike) -> list[list[float]]:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"points must have shape (n, 2); got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("points must be finite")
    out: list[list[float]] = arr.tolist()
    return out


def find_shape_files(
    folder: str | Path, *, pattern: str = "*", recursive: bool = False
) -> list[Path]:
    """The point files and images in ``folder`` whose name matches ``pattern``, sorted by
    their path relative to the folder; other files are skipped.

    Raises
    ------
    FileNotFoundError
        If ``folder`` is not a folder or holds no matching shape file.
    """
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder")
    candidates = root.rglob("*") if recursive else root.iterdir()
    files = sorted(
        (
            p
            for p in candidates
            if p.is_file()
            and p.suffix.lower() in UPLOAD_SUFFIXES
            and fnmatch.fnmatch(p.name, pattern)
        ),
        key=lambda p: str(p.relative_to(root)),
    )
    if not files:
        raise FileNotFoundError(
            f"no shape files matching {pattern!r} in {root} "
            f"(looked for {', '.join(sorted(UPLOAD_SUFFIXES))})"
        )
    return files
