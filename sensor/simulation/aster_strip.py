"""Consecutive ASTER L1A granules of one pass (a strip), simulated.

One long along-track scene is rendered (:func:`stereodem.sensor.simulation.simulate.simulate_scene`,
preset ``aster``: one orbit, one attitude, one time base for the whole pass) and cut into
granules the way the ground segment cuts a pass (ASTER notes ``aster-l1a-format.md`` §1.2, §2.4):

* a 3N granule of ``h`` lines every ``advance`` lines, ``advance = 10 x row_step`` (real
  products: a 4200-line 3N scene every 4000 lines = 10 lattice steps of 400 lines, 5 %
  overlap); the granule length is scaled with the image size as the simulator scales scenes
  (real GSD, line period and orbit; fewer lines), ``row_step`` as
  :func:`stereodem.sensor.simulation.aster_granule.granule_from_scene` picks it (~h / 10.5), so
  consecutive granules overlap by ``h - advance`` lines (about half a lattice step: a few
  lines for small simulated granules) and their lattice rows fall on the same lines;
* the 3B granule ``k`` holds the same ground as 3N granule ``k``: the long 3B image is
  ``hB - h`` lines longer than the long 3N one (both centred on the scene centre), so 3B
  granule ``k`` starts at the same line offset ``k x advance``;
* every granule's models are the long models restarted at its first line (the same ephemeris,
  ``t0`` moved on), its ``ObservationTime`` and metadata times on the pass's one clock, its
  radiometric table the pass's (one seed: the detectors do not change between granules), its
  ``ASTERSCENEID`` ``(path, row + k, 0)`` and its production time ``k`` seconds after the
  first (distinct granule ids; [our choice]).
"""

from __future__ import annotations

import copy
import dataclasses
import datetime as _dt

from stereodem.core import jsonutil
from stereodem.core.errors import InputError
from stereodem.core.raster import write_text_atomic
from stereodem.sensor.simulation.aster_granule import (
    DEFAULT_START,
    granule_from_scene,
    granule_right_size,
    write_v003,
    write_v004,
)
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene


def granule_row_step(height: int) -> int:
    """Lattice row step (lines) of a simulated granule of ``height`` 3N lines (as
    :func:`granule_from_scene` chooses it)."""
    return 400 if height >= 4000 else max(8, int(round(height / 10.5)))


def crop_lines(model, first: int, height: int):
    """A copy of pushbroom ``model`` whose line 0 is its line ``first`` (same ephemeris and
    attitude, ``t0`` moved on by ``first`` line periods), ``height`` lines long."""
    m = copy.copy(model)
    m.t0 = float(model.t0) + int(first) * float(model.line_period)
    m.height = int(height)
    m._guess = None
    return m


def cut_granule(
    scene,
    first: int,
    heights,
    *,
    row_step: int,
    start: _dt.datetime = DEFAULT_START,
    index: int = 0,
    seed: int = 0,
    velocity: str = "inertial",
    version: int = 4,
):
    """The granule (in memory) of 3N lines ``first .. first + heights[0]`` and 3B lines
    ``first .. first + heights[1]`` of a long ``aster`` scene; ``start`` is the time of the
    long scene's 3N line 0 (the granule's own start follows from ``first``)."""
    h, hb = int(heights[0]), int(heights[1])
    if first < 0 or first + h > scene.left.shape[0] or first + hb > scene.right.shape[0]:
        raise InputError(f"granule lines {first}..{first + max(h, hb) - 1} are outside the scene")
    lp = float(scene.left_model.line_period)
    part = dataclasses.replace(
        scene,
        left=scene.left[first : first + h],
        right=scene.right[first : first + hb],
        left_model=crop_lines(scene.left_model, first, h),
        right_model=crop_lines(scene.right_model, first, hb),
    )
    return granule_from_scene(
        part,
        seed=seed,
        velocity=velocity,
        row_step=row_step,
        version=version,
        start=start + _dt.timedelta(seconds=first * lp),
        scene_index=index,
    )


@dataclasses.dataclass
class SimulatedStrip:
    """A simulated pass: the long scene, its granules (in memory) and where each was cut."""

    scene: object  #: the long Scene (truth DEM and orthoimage of the strip)
    granules: list  #: SimulatedGranule per granule, in time order
    first_lines: list  #: 3N (and 3B) line of the long images where granule k starts
    heights: tuple  #: (3N lines, 3B lines) of every granule
    advance: int  #: lines between consecutive granule starts
    row_step: int  #: lattice row step, lines


def simulate_strip(
    n_granules: int = 2,
    *,
    size=(200, 160),
    right_size=None,
    seed: int = 0,
    noise: float = 1.0,
    dem=None,
    texture=None,
    velocity: str = "inertial",
    start: _dt.datetime = DEFAULT_START,
    version: int = 4,
) -> SimulatedStrip:
    """``n_granules`` consecutive granules of one simulated ASTER pass (see the module docstring).

    ``size`` is one granule's 3N (width, lines); ``right_size`` its 3B size (default the real
    3N:3B ratio, :func:`stereodem.sensor.simulation.aster_granule.granule_right_size`).
    """
    n = int(n_granules)
    if n < 1:
        raise InputError(f"a strip needs at least one granule, got {n_granules}")
    w, h = int(size[0]), int(size[1])
    if w % 10:
        raise InputError(f"granule width {w} must be a multiple of 10 (11 lattice columns)")
    wb, hb = (int(right_size[0]), int(right_size[1])) if right_size else granule_right_size((w, h))
    step = granule_row_step(h)
    advance = 10 * step
    if advance >= h:
        raise InputError(f"granules of {h} lines are too short to overlap (lattice step {step})")
    total = advance * (n - 1) + h
    scene = simulate_scene(
        "aster",
        size=(w, total),
        right_size=(wb, total + hb - h),
        dem=dem,
        texture=texture,
        noise=noise,
        seed=seed,
    )
    granules, firsts = [], []
    for k in range(n):
        granules.append(
            cut_granule(
                scene,
                k * advance,
                (h, hb),
                row_step=step,
                start=start,
                index=k,
                seed=seed,
                velocity=velocity,
                version=version,
            )
        )
        firsts.append(k * advance)
    return SimulatedStrip(scene, granules, firsts, (h, hb), advance, step)


def write_strip(strip: SimulatedStrip, out, *, overwrite: bool = False, version: int = 4) -> list:
    """Write the strip's granules (V004 ``.hdf`` or V003 ``.zip``) and the long scene's truth
    (``truth_dem.tif``, ``truth_ortho.tif``, ``points.csv``, ``scene.json``) and ``strip.json``
    (the granule files, where each was cut: 3N/3B first line, lines, the advance and the row
    step) into ``out``; returns the granule paths in time order."""
    folder = write_scene(strip.scene, out, overwrite=overwrite, write_images=False)
    paths = []
    for g in strip.granules:
        if version == 4:
            paths.append(write_v004(g, folder / f"{g.granule_id}.hdf", overwrite=overwrite))
        else:
            paths.append(write_v003(g, folder / f"{g.granule_id}.zip", overwrite=overwrite))
    cut = dict(
        granules=[p.name for p in paths],
        first_lines=strip.first_lines,
        lines_3N=strip.heights[0],
        lines_3B=strip.heights[1],
        advance=strip.advance,
        overlap_3N=strip.heights[0] - strip.advance,
        row_step=strip.row_step,
    )
    write_text_atomic(folder / "strip.json", jsonutil.dumps(cut, indent=2), overwrite=overwrite)
    return paths


__all__ = [
    "SimulatedStrip",
    "crop_lines",
    "cut_granule",
    "granule_row_step",
    "simulate_strip",
    "write_strip",
]
