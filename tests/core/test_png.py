"""``stereodem.core.png.save_png``: the one way the package writes a figure."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

import stereodem.core.png as png  # noqa: E402
from stereodem.core.errors import OutputExistsError  # noqa: E402


def _figure():
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.imshow(np.random.default_rng(0).normal(size=(60, 80)), cmap="gray")
    return fig


def test_writes_a_png_closes_the_figure_and_keeps_the_overwrite_policy(tmp_path):
    path = tmp_path / "f.png"
    fig = _figure()
    assert png.save_png(fig, path, dpi=50) == path
    assert fig.number not in plt.get_fignums()
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size == (150, 100)
    assert [p.name for p in tmp_path.iterdir()] == ["f.png"]  # no temporary left
    fig = _figure()
    with pytest.raises(OutputExistsError, match="f.png: exists"):
        png.save_png(fig, path, dpi=50)
    assert fig.number not in plt.get_fignums()  # closed on failure too
    png.save_png(_figure(), path, dpi=100, overwrite=True)
    with Image.open(path) as im:
        assert im.size == (300, 200)


def test_the_compression_level_is_the_module_constant(tmp_path, monkeypatch):
    """The zlib level reaches the encoder: level 0 stores, level 1 compresses (same pixels)."""
    sizes, pixels = {}, {}
    for level in (0, 1):
        monkeypatch.setattr(png, "PNG_COMPRESS_LEVEL", level)
        path = png.save_png(_figure(), tmp_path / f"l{level}.png", dpi=80)
        sizes[level] = path.stat().st_size
        with Image.open(path) as im:
            pixels[level] = np.asarray(im)
    assert sizes[1] < 0.8 * sizes[0]
    np.testing.assert_array_equal(pixels[0], pixels[1])


def _placed_figure():
    """A figure whose content box lies on whole pixels at 100 dpi (an image in axes without
    axis, a patch, no text): savefig's fractional placement is then a whole one too."""
    from matplotlib.patches import Rectangle

    fig = plt.figure(figsize=(3, 2))
    ax = fig.add_axes((0.2, 0.25, 0.6, 0.5))
    ax.imshow(np.random.default_rng(1).normal(size=(37, 53)), cmap="viridis", aspect="auto")
    ax.set_axis_off()
    fig.patches.append(Rectangle((0.05, 0.1), 0.1, 0.2, transform=fig.transFigure, color="k"))
    return fig


def test_tight_crop_in_one_draw_is_savefig_tight_pixel_for_pixel(tmp_path):
    """save_png(bbox_inches="tight") draws once (core.png._tight_rgba) and gives what
    savefig(bbox_inches="tight") gives, where the content's box lies on whole pixels."""
    draws = []
    fig = _placed_figure()
    fig.canvas.mpl_connect("draw_event", lambda event: draws.append(event))
    png.save_png(fig, tmp_path / "once.png", dpi=100, bbox_inches="tight")
    assert len(draws) == 1
    fig = _placed_figure()
    fig.savefig(tmp_path / "tight.png", dpi=100, bbox_inches="tight")
    with Image.open(tmp_path / "once.png") as a, Image.open(tmp_path / "tight.png") as b:
        assert a.size == b.size == (245, 150)  # 0.05 .. 2.5 in wide, 0.1 .. 1.6 in high
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert a.info.get("dpi") == pytest.approx((100, 100), abs=0.01)


def test_content_beyond_the_margin_takes_savefig_tight(tmp_path):
    """A label further out than TIGHT_MARGIN_IN: no crop in one draw; the PNG is savefig's."""
    fig = _placed_figure()
    fig.text(-png.TIGHT_MARGIN_IN / 3 - 0.2, 0.5, "far out", fontsize=20)
    assert png._tight_rgba(fig, 100) is None
    png.save_png(fig, tmp_path / "once.png", dpi=100, bbox_inches="tight")
    fig = _placed_figure()
    fig.text(-png.TIGHT_MARGIN_IN / 3 - 0.2, 0.5, "far out", fontsize=20)
    fig.savefig(tmp_path / "tight.png", dpi=100, bbox_inches="tight")
    with Image.open(tmp_path / "once.png") as a, Image.open(tmp_path / "tight.png") as b:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
