"""Which poses the affine pre-alignment may take: one option, four documented modes.

The affine ICP of eqs. 2-9 is local, so it is started from several poses. How far those
starts may turn the model decides what the pre-alignment can find, and what it can get
wrong: on glyphs, the best D over every orientation and reflection is often a rotated or
mirrored pose, and CPD started there lands on the subject with a small e (eq. 10) and
wrong correspondences.

Modes (``pose=``):

``"as_given"``
    Only the shapes as given: ICP starts from the identity on the size-normalised shapes
    (centroids matched, unit RMS radius) and converges locally.
``"upright"``
    Rotations within +-``max_rotation`` degrees of the shapes as given (default 30), no
    reflection. For collections known to be upright: glyph scans, aligned outlines.
``"rotation"`` (the default)
    Any rotation, no reflection: ``det(A) > 0`` throughout ICP.
``"affine"``
    Any affine map with ``det(A) != 0``, reflections included (the paper's eq. 2).

In every mode the pose as given is always a candidate, and a differently rotated pose has
to earn its place by the registration it leads to, not by D alone (see the tree's
``_register_task``): it replaces the pose as given only when CPD from it reaches an error
well below CPD from the pose as given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = [
    "DEFAULT_POSE", "POSE_MODES", "PoseMode", "PoseSpec", "angle_between", "rotation_angle",
]

PoseMode = Literal["as_given", "upright", "rotation", "affine"]
POSE_MODES: tuple[str, ...] = get_args(PoseMode)
DEFAULT_POSE: PoseMode = "rotation"
#: Half-width of the "upright" mode when no max_rotation is given, in degrees.
DEFAULT_UPRIGHT_DEG = 30.0


@dataclass(frozen=True)
class PoseSpec:
    """A validated pose option: the mode and, for ``"upright"``, its half-width in degrees."""

    mode: PoseMode = DEFAULT_POSE
    max_rotation: float | None = None

    @classmethod
    def resolve(cls, pose: str | None, max_rotation: float | None) -> PoseSpec:
        """Validate ``pose`` and ``max_rotation`` together.

        ``max_rotation`` alone (the option of earlier versions) means ``"upright"``; with
        ``pose="upright"`` and no ``max_rotation`` the half-width is 30 degrees.

        Raises
        ------
        ValueError
            On an unknown mode, a max_rotation outside [0, 180], or a max_rotation given
            with a mode other than "upright".
        """
        if max_rotation is not None:
            if not (isinstance(max_rotation, int | float) and math.isfinite(max_rotation)
                    and 0 <= max_rotation <= 180):
                raise ValueError(f"max_rotation must be in [0, 180] degrees; got {max_rotation}")
        if pose is None:
            pose = "upright" if max_rotation is not None else DEFAULT_POSE
        if pose not in POSE_MODES:
            modes = ", ".join(map(repr, POSE_MODES))
            raise ValueError(f"pose must be one of {modes}; got {pose!r}")
        if max_rotation is not None and pose != "upright":
            raise ValueError(
                f"max_rotation only applies to pose='upright'; got pose={pose!r} with "
                f"max_rotation={max_rotation}"
            )
        if pose == "upright":
            return cls(mode="upright", max_rotation=float(
                DEFAULT_UPRIGHT_DEG if max_rotation is None else max_rotation))
        return cls(mode=pose)  # type: ignore[arg-type]

    @property
    def allow_reflection(self) -> bool:
        return self.mode == "affine"

    @property
    def any_rotation(self) -> bool:
        """Whether every turn may be tried (``"rotation"`` and ``"affine"``), not only
        those within ``max_rotation`` of the pose as given (``"upright"``) or none
        (``"as_given"``)."""
        return self.mode in ("rotation", "affine")

    def to_dict(self) -> dict[str, object]:
        return {"pose": self.mode, "max_rotation": self.max_rotation}


def rotation_angle(A: FloatArray) -> float:
    """Angle in degrees of the rotation nearest to ``A`` (its polar factor), in (-180, 180].

    For a map with ``det(A) < 0`` this is the angle of the nearest rotation-reflection's
    rotation part, so compare handedness (the sign of ``det(A)``) separately.
    """
    a = np.asarray(A, dtype=np.float64)
    if np.linalg.det(a) < 0:
        a = a @ np.diag([1.0, -1.0])
    return float(np.degrees(np.arctan2(a[1, 0] - a[0, 1], a[0, 0] + a[1, 1])))


def angle_between(a_deg: float, b_deg: float) -> float:
    """Smallest absolute difference of two angles in degrees, in [0, 180]."""
    d = (a_deg - b_deg + 180.0) % 360.0 - 180.0
    return abs(d)
