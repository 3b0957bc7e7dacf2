"""Whether a user's camera-to-world is a rigid pose, checked in plain Python: the request schemas
that the API validates (workers/render/schemas.py) use it, and the API process does not load
PyTorch."""

from __future__ import annotations

import math
from typing import Sequence

ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| and |det R - 1| a user's camera-to-world may have


def rigid_error(c2w: Sequence[Sequence[float]]) -> float:
    """max |R^T R - I| and |det R - 1| of the 3x3 block of a 3x4 (or 4x4) pose: zero for a rigid
    one."""
    r = [[float(v) for v in row[:3]] for row in c2w[:3]]
    ortho = max(
        abs(sum(r[k][i] * r[k][j] for k in range(3)) - (i == j)) for i in range(3) for j in range(3)
    )
    det = (
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
    )
    return max(ortho, abs(det - 1))


def rotation_problem(c2w: Sequence[Sequence[float]]) -> str | None:
    """What is wrong with a camera-to-world's 3x4 block, or None."""
    if not all(math.isfinite(float(v)) for row in c2w[:3] for v in row):
        return "holds a value that is not a finite number"
    error = rigid_error(c2w)
    if error > ROTATION_TOLERANCE:
        return (
            f"its 3x3 block is not a rotation (max |R^T R - I|, |det R - 1| = {error:.3g}, more "
            f"than {ROTATION_TOLERANCE:g}): give an orthonormal, right-handed camera-to-world"
        )
    return None
