"""ASP binary ``.match`` files: read, write back byte for byte, refuse those of other images."""

from pathlib import Path

import numpy as np
import pytest

from stereodem.core.errors import InputError
from stereodem.sensor.io.asp_match import (
    InterestPoints,
    MatchFile,
    check_match_images,
    match_stems,
    read_match,
    write_match,
)
from stereodem.sensor.io.aster_xml import bundled_xml
from stereodem.sensor.models.aster import AsterModel
from stereodem.stereo.ties import check_match_geometry

HERE = Path(__file__).resolve().parent
SMALL = HERE.parent / "data" / "asp" / "run-out-Band3N__out-Band3B.match"
FULL = next(
    (
        p / "shared" / "data" / "aster_fixture" / "run-out-Band3N__out-Band3B.match"
        for p in HERE.parents
        if (p / "shared" / "data" / "aster_fixture" / "run-out-Band3N__out-Band3B.match").is_file()
    ),
    None,
)


@pytest.fixture(scope="module")
def models():
    return AsterModel.from_xml(bundled_xml("3N")), AsterModel.from_xml(bundled_xml("3B"))


def test_read_real_matches(models):
    m = read_match(SMALL)
    assert len(m) == 60 and m.ties().shape == (60, 4)
    assert {len(d) for d in m.left.descriptors} == {180}  # ASP's default descriptor
    n, b = models
    # the real 3N/3B matches lie on their epipolar curves (ASP and stereodem agree on pixel centres)
    info = check_match_images(
        m,
        "out-Band3N.tif",
        "out-Band3B.tif",
        left_size=(n.width, n.height),
        right_size=(b.width, b.height),
    )
    assert info["n_matches"] == 60
    assert check_match_geometry(m, n, b, (0.0, 4400.0)) < 5.0


def test_write_back_byte_for_byte(tmp_path):
    for k, src in enumerate([SMALL] + ([FULL] if FULL else [])):
        m = read_match(src)
        out = write_match(tmp_path / f"{k}" / src.name, m)
        assert out.read_bytes() == src.read_bytes()
        with pytest.raises(Exception, match="exists"):
            write_match(out, m)
    if FULL:
        assert len(read_match(FULL)) == 1145
    # points of our own (no descriptors) round trip too
    pts = MatchFile(
        InterestPoints(np.array([1.5, 2.25]), np.array([3.0, 4.0])),
        InterestPoints(np.array([5.0, 6.0]), np.array([7.0, 8.5])),
    )
    back = read_match(write_match(tmp_path / "own.match", pts))
    np.testing.assert_array_equal(back.ties(), [[1.5, 3.0, 5.0, 7.0], [2.25, 4.0, 6.0, 8.5]])


def test_refuses_match_of_other_images(models, tmp_path):
    m = read_match(SMALL)
    n, b = models
    assert match_stems(SMALL) == ("run-out-Band3N", "out-Band3B")
    with pytest.raises(InputError, match="other order"):
        check_match_images(m, "out-Band3B.tif", "out-Band3N.tif")
    with pytest.raises(InputError, match="named for other images"):
        check_match_images(m, "left.tif", "right.tif")
    # the same points under a neutral name: the geometry refuses them for the swapped pair
    plain = read_match(write_match(tmp_path / "pair.match", m))
    with pytest.raises(InputError, match="across the epipolar curves"):
        swapped = MatchFile(plain.right, plain.left, str(tmp_path / "pair.match"))
        check_match_images(swapped, "3B", "3N")  # the name says nothing
        check_match_geometry(swapped, n, b, (0.0, 4400.0), names=("3B", "3N"))
    with pytest.raises(InputError, match="outside"):
        check_match_images(plain, "small.tif", "3B.tif", left_size=(500, 500))


@pytest.mark.parametrize("damage", ["truncated", "text", "trailing", "empty"])
def test_damaged_files_are_one_line_errors(tmp_path, damage):
    data = SMALL.read_bytes()
    bad = {
        "truncated": data[:-100],
        "text": b"not a match file at all\n" * 4,
        "trailing": data + b"\0\0",
        "empty": b"",
    }[damage]
    p = tmp_path / "x.match"
    p.write_bytes(bad)
    with pytest.raises(InputError, match="x.match"):
        read_match(p)
