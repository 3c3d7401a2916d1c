"""Image pyramids for coarse-to-fine matching, NaN-aware.

Level ``l + 1`` is OpenCV's ``pyrDown`` of level ``l`` (5x5 Gaussian, then every second
pixel): coarse pixel ``(i, j)`` sits on fine pixel ``(2i, 2j)``, pixel centres at integer
coordinates as everywhere in stereodem.  NaN marks no-data; a coarse pixel whose Gaussian
support touches no-data is NaN too, so no-data never leaks into valid values.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["downsample", "build_pyramid", "upsample_field"]


def downsample(image):
    """Halve ``image`` (float32, NaN = no-data) with ``cv2.pyrDown``.

    Parameters
    ----------
    image : ndarray (H, W)
        Float image; NaN marks no-data.

    Returns
    -------
    ndarray ((H + 1) // 2, (W + 1) // 2), float32
        Coarse image; NaN where the 5x5 Gaussian support touched no-data.
    """
    image = np.asarray(image, dtype=np.float32)
    valid = np.isfinite(image)
    if valid.all():
        return cv2.pyrDown(image)
    filled = np.where(valid, image, np.float32(0.0))
    weight = cv2.pyrDown(valid.astype(np.float32))
    coarse = cv2.pyrDown(filled)
    out = np.full(coarse.shape, np.nan, dtype=np.float32)
    ok = weight > 0.999
    out[ok] = coarse[ok] / weight[ok]
    return out


def build_pyramid(image, levels):
    """List ``[image, image/2, ..., image/2**levels]`` of NaN-aware pyramid levels."""
    pyramid = [np.asarray(image, dtype=np.float32)]
    for _ in range(levels):
        pyramid.append(downsample(pyramid[-1]))
    return pyramid


def upsample_field(field, shape, *, scale=2.0):
    """Bring a coarse per-pixel field (e.g. a disparity) to the next finer level.

    Fine pixel ``(x, y)`` reads the coarse field at ``(x / 2, y / 2)`` (bilinear, edges
    replicated), consistent with :func:`downsample`; values are multiplied by ``scale``
    (2 for disparities in pixels, 1 for masks or scores).

    Parameters
    ----------
    field : ndarray (h, w), float32, no NaN
    shape : tuple (H, W)
        Shape of the finer level.
    """
    h, w = shape
    xs = np.arange(w, dtype=np.float32) * np.float32(0.5)
    ys = np.arange(h, dtype=np.float32) * np.float32(0.5)
    map_x = np.broadcast_to(xs[None, :], (h, w))
    map_y = np.broadcast_to(ys[:, None], (h, w))
    fine = cv2.remap(
        np.asarray(field, dtype=np.float32),
        np.ascontiguousarray(map_x),
        np.ascontiguousarray(map_y),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    if scale != 1.0:
        fine *= np.float32(scale)
    return fine
