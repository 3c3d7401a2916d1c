"""Morphology of boolean masks by OpenCV (uint8 views of the masks, no copies of the grids).

One operation the filters, the hole filling and the matcher share: the cells whose square
window holds a ``True`` cell, outside the grid counting as ``False``. It equals
``scipy.ndimage.binary_dilation`` with a square structuring element of that side, about 20×
faster (tested).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["square_dilation"]


def square_dilation(mask, size: int) -> np.ndarray:
    """Boolean mask of the cells whose ``size`` × ``size`` window (``size`` odd, centred on
    the cell) holds a ``True`` cell of ``mask``; the cells outside the grid count as
    ``False``. A new array."""
    m = np.ascontiguousarray(mask, dtype=bool)
    k = np.ones((int(size), int(size)), np.uint8)
    return cv2.dilate(m.view(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
