"""Linear stretch of an image to 8 bits, the one implementation the matchers share.

``round-half-up((a - lo) * scale)`` clipped to 0..255, computed in float64 by bands of rows
through one 1 MiB buffer that stays in cache: the same bits as the whole-image float64
formula, without its full-size float64 temporaries (a 5000 × 5400 ASTER band would need
216 MB of them, paid in page faults on first touch).
"""

from __future__ import annotations

import numpy as np

__all__ = ["linear_to_uint8"]

_BUFFER_BYTES = 1 << 20  # float64 rows per band: 1 MiB


def linear_to_uint8(a, lo, scale) -> np.ndarray:
    """``a`` (2-D, any real dtype) mapped to uint8 by ``(a - lo) * scale + 0.5`` in float64,
    clipped to 0..255 and truncated (round half up); NaN gives an unspecified value: the
    caller sets its own no-data value where it needs one."""
    a = np.asarray(a)
    b = np.empty(a.shape, np.uint8)
    if a.size == 0:
        return b
    step = max(1, (_BUFFER_BYTES // 8) // max(a.shape[1], 1))
    buf = np.empty((step, a.shape[1]), np.float64)
    with np.errstate(invalid="ignore"):  # NaN: set by the caller
        for r in range(0, a.shape[0], step):
            blk = buf[: min(step, a.shape[0] - r)]
            # float64 stated: numpy 1 subtracts a float scalar from float32 in float32
            np.subtract(a[r : r + step], lo, out=blk, dtype=np.float64)
            np.multiply(blk, scale, out=blk)
            np.add(blk, 0.5, out=blk)
            np.clip(blk, 0, 255, out=blk)
            np.copyto(b[r : r + step], blk, casting="unsafe")
    return b
