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
