"""PNG files of matplotlib figures: one rule for every figure the package writes.

Every figure goes through :func:`save_png`: the overwrite policy
(:func:`~stereodem.core.raster.check_writable`), an atomic write
(:func:`~stereodem.core.raster.atomic_path`), the figure closed afterwards, one zlib level
(:data:`PNG_COMPRESS_LEVEL`), and the figure cropped to its content
(``bbox_inches="tight"``) in one draw (:func:`_tight_rgba`).
"""

from __future__ import annotations

import io

import numpy as np

from stereodem.core.raster import atomic_path, check_writable

#: zlib level of the PNGs: 1 encodes the assessment's four figures in about half the time of
#: Pillow's default 6 (74 against 140 ms on the full-granule report, one core), with files
#: between 10 % smaller and 10 % larger (a shaded relief compresses worst: +10 %)
PNG_COMPRESS_LEVEL = 1

#: inches of canvas drawn around a figure in which :func:`_tight_rgba` looks for its content
#: (labels and titles may reach beyond the figure's edge: a colour bar's label, a y-axis
#: label left of a map); content reaching further takes ``savefig``'s own two draws
TIGHT_MARGIN_IN = 1.0


def save_png(fig, path, *, dpi: float, overwrite: bool = False, bbox_inches=None):
    """Write ``fig`` (a matplotlib figure) to ``path`` as a PNG of ``dpi`` dots per inch,
    atomically, then close it; returns the path. ``bbox_inches``: as ``Figure.savefig``
    (None: the whole figure; ``"tight"``: cropped to the content, drawn once,
    :func:`_tight_rgba`). Raises :class:`~stereodem.core.errors.OutputExistsError` when
    ``path`` exists and ``overwrite`` is False (the figure is closed either way)."""
    import matplotlib.image
    import matplotlib.pyplot as plt

    try:
        path = check_writable(path, overwrite)
        rgba = _tight_rgba(fig, dpi) if _is_tight(bbox_inches) else None
        pil = {"compress_level": PNG_COMPRESS_LEVEL}
        with atomic_path(path) as tmp:
            if rgba is not None:  # matplotlib's own PNG writer, as savefig's
                matplotlib.image.imsave(tmp, rgba, format="png", dpi=dpi, pil_kwargs=pil)
            else:
                fig.savefig(tmp, dpi=dpi, bbox_inches=bbox_inches, format="png", pil_kwargs=pil)
    finally:
        plt.close(fig)
    return path


def _is_tight(bbox_inches) -> bool:
    return isinstance(bbox_inches, str) and bbox_inches == "tight"


def _tight_rgba(fig, dpi: float) -> np.ndarray | None:
    """The pixels (RGBA, uint8, rows top down) of ``savefig(bbox_inches="tight")`` in one draw
    instead of its two; None where the content reaches beyond :data:`TIGHT_MARGIN_IN`.

    ``"tight"`` draws the figure once to measure its content's box (the text extents), then
    again cropped to it: two draws, each as long (the axes, ticks and labels dominate; about
    0.1-0.3 s per figure). Here the figure is drawn once on a canvas
    :data:`TIGHT_MARGIN_IN` wider on every side (``savefig``'s own ``bbox_inches`` with a box
    larger than the figure), the content's box is measured with that draw's renderer, and
    the canvas is cropped to it: the same size (``int`` of the box in pixels, as Agg sizes
    its canvas) and the same picture, placed to the nearest pixel instead of a fraction of
    one (images resampled on that grid differ in single cells; text and lines by
    anti-aliasing)."""
    import matplotlib.pyplot as plt
    from matplotlib.transforms import Bbox

    w, h = fig.get_size_inches()
    m = TIGHT_MARGIN_IN
    canvas_box = Bbox.from_extents(-m, -m, w + m, h + m)
    drawn = {}

    def measure(event):  # after the draw, in the canvas's frame (origin at its corner)
        drawn["box"] = fig.get_tightbbox(event.renderer)
        drawn["size"] = int(event.renderer.width), int(event.renderer.height)

    cid = fig.canvas.mpl_connect("draw_event", measure)
    try:
        buf = io.BytesIO()
        fig.savefig(buf, format="rgba", dpi=dpi, bbox_inches=canvas_box)
    finally:
        fig.canvas.mpl_disconnect(cid)
    if "box" not in drawn:
        return None
    cw, ch = drawn["size"]
    box = drawn["box"].padded(plt.rcParams["savefig.pad_inches"])
    width, height = int(box.width * dpi), int(box.height * dpi)
    c0 = int(round(box.x0 * dpi))
    bottom = ch - int(round(box.y0 * dpi))  # rows top down; the box's bottom edge
    r0 = bottom - height
    if c0 < 0 or r0 < 0 or c0 + width > cw or bottom > ch or width < 1 or height < 1:
        return None
    rgba = np.frombuffer(buf.getbuffer(), np.uint8).reshape(ch, cw, 4)
    return np.ascontiguousarray(rgba[r0:bottom, c0 : c0 + width])
