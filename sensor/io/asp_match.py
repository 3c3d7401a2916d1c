"""ASP's binary interest-point match files (``*.match``): read, write, check against images.

Layout (little-endian; Ames Stereo Pipeline / VisionWorkbench ``ip::write_binary_match_file``):
two uint64 counts (points of image 1, of image 2), then each image's interest points in turn,
each as::

    x, y            float32   sub-pixel position (col, row; pixel centres at integers,
                              stereodem's convention)
    ix, iy          int32     integer position
    orientation, scale, interest   float32
    polarity        bool      1 byte
    octave, scale_lvl  uint32
    n               uint64    descriptor length
    descriptor      n x float32

Point ``k`` of image 1 matches point ``k`` of image 2. ASP names the file after the two
images: ``<prefix>-<stem1>__<stem2>.match``; the file itself does not name them, so a file of
other images can only be caught by that name and by the geometry: :func:`check_match_images`
refuses matches whose points fall outside the images, and
:func:`stereodem.stereo.ties.check_match_geometry`, given the sensor models, those that lie far
across their epipolar curves (read ``../shared/notes/dem-correction-and-stacks.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core.errors import InputError, not_found
from stereodem.core.raster import atomic_path, check_writable

__all__ = [
    "InterestPoints",
    "MatchFile",
    "read_match",
    "write_match",
    "check_match_images",
    "match_stems",
]

_HEAD = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("ix", "<i4"),
        ("iy", "<i4"),
        ("orientation", "<f4"),
        ("scale", "<f4"),
        ("interest", "<f4"),
        ("polarity", "u1"),
        ("octave", "<u4"),
        ("scale_lvl", "<u4"),
        ("n_desc", "<u8"),
    ]
)


@dataclass
class InterestPoints:
    """One image's interest points of a match file (arrays of equal length; ``descriptors``
    a list of float32 arrays, possibly of different lengths)."""

    x: np.ndarray
    y: np.ndarray
    ix: np.ndarray = None
    iy: np.ndarray = None
    orientation: np.ndarray = None
    scale: np.ndarray = None
    interest: np.ndarray = None
    polarity: np.ndarray = None
    octave: np.ndarray = None
    scale_lvl: np.ndarray = None
    descriptors: list = field(default_factory=list)

    def __post_init__(self):
        n = len(self.x)
        defaults = dict(
            ix=np.rint(self.x),
            iy=np.rint(self.y),
            orientation=0.0,
            scale=1.0,
            interest=0.0,
            polarity=0,
            octave=0,
            scale_lvl=0,
        )
        for name, dtype in (
            ("ix", np.int32),
            ("iy", np.int32),
            ("orientation", np.float32),
            ("scale", np.float32),
            ("interest", np.float32),
            ("polarity", np.uint8),
            ("octave", np.uint32),
            ("scale_lvl", np.uint32),
        ):
            v = getattr(self, name)
            setattr(
                self,
                name,
                np.broadcast_to(np.asarray(defaults[name] if v is None else v), (n,)).astype(dtype),
            )
        self.x, self.y = np.asarray(self.x, np.float32), np.asarray(self.y, np.float32)
        if not self.descriptors:
            self.descriptors = [np.zeros(0, np.float32)] * n

    def __len__(self):
        return len(self.x)


@dataclass
class MatchFile:
    """The two images' matched points: ``left[k]`` matches ``right[k]``."""

    left: InterestPoints
    right: InterestPoints
    path: str | None = None

    def __len__(self):
        return len(self.left)

    def ties(self) -> np.ndarray:
        """``(n, 4)`` float64 array ``col1, row1, col2, row2`` (the tie-point layout of
        :func:`stereodem.sensor.estimation.adjust.bundle.bundle_adjust`)."""
        return np.column_stack([self.left.x, self.left.y, self.right.x, self.right.y]).astype(
            np.float64
        )


def _read_points(buf: bytes, pos: int, n: int, path) -> tuple:
    """``n`` interest points from ``buf`` at ``pos``; returns (InterestPoints, new pos)."""
    heads = np.zeros(n, _HEAD)
    descs = []
    size = _HEAD.itemsize
    for k in range(n):  # records have their own descriptor length: walk them (n is small)
        if pos + size > len(buf):
            raise InputError(f"{path}: truncated ASP match file (point {k + 1} of {n})")
        h = np.frombuffer(buf, _HEAD, 1, pos)[0]
        pos += size
        m = int(h["n_desc"])
        if m > 4096 or pos + 4 * m > len(buf):
            raise InputError(
                f"{path}: not an ASP match file (descriptor length {m} at point {k + 1})"
            )
        heads[k] = h
        descs.append(np.frombuffer(buf, "<f4", m, pos).copy())
        pos += 4 * m
    pts = InterestPoints(
        heads["x"],
        heads["y"],
        heads["ix"],
        heads["iy"],
        heads["orientation"],
        heads["scale"],
        heads["interest"],
        heads["polarity"],
        heads["octave"],
        heads["scale_lvl"],
        descs,
    )
    return pts, pos


def read_match(path) -> MatchFile:
    """Read an ASP binary ``.match`` file; :class:`InputError` (one line naming the file)
    when it is not one (truncated, trailing bytes, unequal counts)."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except FileNotFoundError:
        raise InputError(not_found(path, "match file")) from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not an ASP match file") from None
    if len(buf) < 16:
        raise InputError(f"{path}: not an ASP match file ({len(buf)} bytes)")
    n1, n2 = (int(v) for v in np.frombuffer(buf, "<u8", 2, 0))
    if n1 != n2 or n1 * _HEAD.itemsize * 2 > len(buf):
        raise InputError(
            f"{path}: not an ASP match file (counts {n1} and {n2} for {len(buf)} bytes)"
        )
    left, pos = _read_points(buf, 16, n1, path)
    right, pos = _read_points(buf, pos, n2, path)
    if pos != len(buf):
        raise InputError(f"{path}: not an ASP match file ({len(buf) - pos} bytes after the points)")
    return MatchFile(left, right, str(path))


def _points_bytes(p: InterestPoints) -> bytes:
    heads = np.zeros(len(p), _HEAD)
    for name in _HEAD.names[:-1]:
        heads[name] = getattr(p, name)
    heads["n_desc"] = [len(d) for d in p.descriptors]
    parts = []
    for k in range(len(p)):
        parts.append(heads[k : k + 1].tobytes())
        parts.append(np.asarray(p.descriptors[k], "<f4").tobytes())
    return b"".join(parts)


def write_match(path, match: MatchFile, *, overwrite: bool = False) -> Path:
    """Write ``match`` as an ASP binary ``.match`` file (atomically; ASP reads it back, e.g.
    ``bundle_adjust --match-files-prefix``). Points without descriptors get empty ones."""
    if len(match.left) != len(match.right):
        raise InputError(f"{path}: {len(match.left)} left and {len(match.right)} right points")
    data = (
        np.array([len(match.left), len(match.right)], "<u8").tobytes()
        + _points_bytes(match.left)
        + _points_bytes(match.right)
    )
    path = check_writable(path, overwrite)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)
    return path


def match_stems(path) -> tuple | None:
    """The two image stems ASP's file name gives (``<prefix>-<stem1>__<stem2>.match``), or None
    when the name does not follow that pattern."""
    name = Path(path).name
    if not name.endswith(".match") or "__" not in name:
        return None
    a, b = name[: -len(".match")].rsplit("__", 1)
    return a, b


def check_match_images(
    match: MatchFile, left_name, right_name, *, left_size=None, right_size=None
) -> dict:
    """Refuse (:class:`InputError`, one line) a match file that belongs to other images.

    Two checks, each when its inputs are given: the file name (ASP's
    ``<prefix>-<stem1>__<stem2>.match`` must end with the left image's stem before ``__``
    and be the right image's stem after it); the points inside the images (``*_size`` =
    (width, height)). The third, geometric check (the points on the models' epipolar curves)
    is :func:`stereodem.stereo.ties.check_match_geometry`. Returns the measured figures.
    """
    path = match.path or "match file"
    out = dict(n_matches=len(match))
    if len(match) == 0:
        raise InputError(f"{path}: holds no match")
    stems = match_stems(path) if match.path else None
    ls, rs = Path(str(left_name)).stem, Path(str(right_name)).stem
    if stems is not None:
        a, b = stems
        if not ((a == ls or a.endswith("-" + ls)) and b == rs):
            swapped = (a == rs or a.endswith("-" + rs)) and b == ls
            raise InputError(
                f"{path}: "
                + (
                    "names the images in the other order"
                    if swapped
                    else "is named for other images"
                )
                + f" (for {ls} then {rs}, ASP writes <prefix>-{ls}__{rs}.match)"
            )
    for side, pts, size in (("left", match.left, left_size), ("right", match.right, right_size)):
        if size is None:
            continue
        w, h = size
        outside = (pts.x < -0.5) | (pts.x > w - 0.5) | (pts.y < -0.5) | (pts.y > h - 0.5)
        if outside.mean() > 0.01:
            raise InputError(
                f"{path}: {100 * outside.mean():.0f} % of its {side} points lie outside "
                f"{left_name if side == 'left' else right_name} ({w}x{h}): the match file "
                "of other images"
            )
    return out
