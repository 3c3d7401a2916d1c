"""``stereodem simulate``: render a stereo pair from a DEM and a texture."""

from __future__ import annotations

import argparse
import json
import logging

from stereodem.core.errors import InputError
from stereodem.core.vertical import VERTICALS

from . import options
from .commands import help_line
from .outlock import Products

#: what ``stereodem simulate`` writes into its output folder (:func:`stereodem.sensor.
#: simulation.simulate.write_scene`, the granules of ``--format l1a-*`` and a strip's
#: ``strip.json``)
PRODUCTS = Products(
    (
        "left.tif",
        "right.tif",
        "left.model.json",
        "right.model.json",
        "truth_dem.tif",
        "truth_ortho.tif",
        "points.csv",
        "scene.json",
        "strip.json",
        "AST_L1A_*.hdf",
        "AST_L1A_*.zip",
    ),
    markers=("scene.json",),
)

log = logging.getLogger(__name__)

FORMATS = ("geotiff", "l1a-v004", "l1a-v003")

EXAMPLES = """examples:
  stereodem simulate --preset aster -o sim_aster
  stereodem simulate --preset aster --format l1a-v004 --size 820 840 -o sim_granule
  stereodem simulate --preset aster --format l1a-v003 --jitter 3 1.5 -o sim_v003
  stereodem simulate --preset aster --format l1a-v004 --granules 2 --size 400 320 -o sim_strip
  stereodem simulate --preset aster --roll-jitter 10 1.2 -o sim_roll
  stereodem simulate --preset frame --size 800 800 --noise 2 --seed 7 -o sim_frame
  stereodem simulate --preset pushbroom --angles 20 -20 --dem my_dem.tif --dem-vertical geoid -o sim
"""


def add_parser(sub):
    p = sub.add_parser(
        "simulate",
        help=help_line("simulate"),
        description="Render a stereo pair through exact sensor models from a real DEM "
        "and texture; write images with RPCs, physical-model sidecars, "
        "the true DEM and orthoimage, and check points. With --format "
        "l1a-v004 / l1a-v003 (preset aster) the pair is written as an "
        "ASTER L1A granule (3N = left, 3B = right) instead of GeoTIFFs, named "
        "AST_L1A_00<v><acquired MMDDYYYYHHMMSS>_<produced YYYYMMDDHHMMSS> as real granules; "
        "the production stamp follows --seed, so granules of different seeds can share "
        "a folder.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--preset",
        choices=["aster", "frame", "pushbroom"],
        default="aster",
        help="scene geometry: aster (the bundled granule's orbit and 3N/3B pointing, 15 m), "
        "frame (a BILSAT-like frame camera, two converging exposures) or pushbroom (a "
        "generic along-track pair, tilts from --angles) (default aster)",
    )
    p.add_argument(
        "--format",
        choices=FORMATS,
        default="geotiff",
        help="geotiff (default): left/right.tif + model sidecars; l1a-v004: an "
        "AST_L1A_004 HDF-EOS2 granule; l1a-v003: an AST_L1A_003 zip of GeoTIFFs "
        "and text tables (aster preset only)",
    )
    p.add_argument("--dem", help='DEM GeoTIFF (default: the bundled SRTM 3" DEM, EGM96 heights)')
    p.add_argument(
        "--dem-vertical",
        choices=VERTICALS,
        help="vertical reference of --dem when the file does not say",
    )
    p.add_argument(
        "--texture", help="texture image (default: the bundled Landsat image plus detail)"
    )
    p.add_argument(
        "--size",
        nargs=2,
        type=int,
        default=[600, 600],
        metavar=("W", "H"),
        help="image size in pixels (the left image's with --right-size) (default 600 600)",
    )
    p.add_argument(
        "--right-size",
        nargs=2,
        type=int,
        metavar=("W", "H"),
        help="size of the second image if different (ASTER 3B: 5000 5400 for 3N's "
        "4100 4200; granule formats default to that ratio)",
    )
    p.add_argument("--noise", type=float, default=1.0, help="sensor noise sigma in DN (default 1)")
    p.add_argument(
        "--seed", type=int, default=0, help="random seed of texture detail and noise (default 0)"
    )
    p.add_argument(
        "--bits", type=int, choices=[8, 16], default=8, help="image quantisation (default 8)"
    )
    p.add_argument(
        "--angles",
        nargs=2,
        type=float,
        default=[0.0, -27.6],
        metavar=("A1", "A2"),
        help="along-track tilts in degrees for --preset pushbroom",
    )
    p.add_argument(
        "--jitter",
        nargs=2,
        type=float,
        metavar=("AMPLITUDE_URAD", "FREQUENCY_HZ"),
        help="along-track attitude oscillation (pitch) of the second camera (3B); "
        "the written model/granule geometry stays nominal, as in L1A products",
    )
    p.add_argument(
        "--roll-jitter",
        nargs=2,
        type=float,
        metavar=("AMPLITUDE_URAD", "FREQUENCY_HZ"),
        help="cross-track attitude oscillation (roll) of the second camera (3B), seen as "
        "residual vertical parallax; may be combined with --jitter",
    )
    p.add_argument(
        "--velocity",
        choices=["inertial", "earth_fixed"],
        default="inertial",
        help="what the granule's SatelliteVelocity holds (default inertial)",
    )
    p.add_argument(
        "--granules",
        type=int,
        default=1,
        metavar="N",
        help="with --format l1a-v004/l1a-v003: N consecutive granules of one pass "
        "(--size is one granule's 3N size; one granule every 10 lattice steps, "
        "about 95 %% of its lines, as the real 4200-line granules every 4000 "
        "lines), plus the strip's truth and strip.json",
    )
    p.add_argument("-o", "--out", required=True, help="output folder")
    options.add_workers(p, "threads of the rendering (OpenCV, BLAS) and the GeoTIFF compression")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    from stereodem.core.dem import DEM
    from stereodem.sensor.simulation.aster_granule import granule_right_size, write_granule_scene
    from stereodem.sensor.simulation.simulate import simulate_scene, write_scene

    from .outlock import check_output_folder, output_folder

    granule = args.format != "geotiff"
    if granule and args.preset != "aster":
        raise InputError(f"--format {args.format} needs --preset aster (an ASTER granule)")
    if granule and args.size[0] % 10:
        raise InputError(
            f"--size width {args.size[0]} must be a multiple of 10 for an ASTER "
            f"granule (11 lattice columns)"
        )
    if args.granules < 1:
        raise InputError(f"--granules must be at least 1, got {args.granules}")
    if args.granules > 1 and not granule:
        raise InputError("--granules needs --format l1a-v004 or l1a-v003 (ASTER granules)")
    if args.granules > 1 and (args.jitter or args.roll_jitter):
        raise InputError("--granules does not combine with --jitter/--roll-jitter")
    # an input among the products (--dem s/truth_dem.tif -o s) was replaced with --overwrite
    inputs = [args.dem, args.texture]
    check_output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs)
    dem = DEM.from_file(args.dem, vertical=args.dem_vertical) if args.dem else None
    if args.granules > 1:
        return _run_strip(args, dem, inputs)
    right_size = (
        tuple(args.right_size)
        if args.right_size
        else (granule_right_size(args.size) if granule else None)
    )
    log.info("simulating %s scene %dx%d", args.preset, *args.size)
    scene = simulate_scene(
        args.preset,
        size=tuple(args.size),
        right_size=right_size,
        dem=dem,
        texture=args.texture,
        noise=args.noise,
        seed=args.seed,
        bits=args.bits,
        angles=tuple(args.angles),
        jitter=args.jitter,
        roll_jitter=args.roll_jitter,
    )
    if not granule:
        with output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs) as out:
            write_scene(scene, out, overwrite=True)
        meta = json.loads((out / "scene.json").read_text())
        options.say(
            f"wrote {out}/left.tif, right.tif (+ .model.json), truth_dem.tif, truth_ortho.tif, "
            "points.csv"
        )
        for name, rep in meta.get("rpc_fit", {}).items():
            options.say(
                f"  {name}: RPC fit check-grid residual rms "
                f"{rep.get('check_rms', float('nan')):.4f} px"
            )
        return 0
    with output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs) as out:
        path = write_granule_scene(
            scene,
            out,
            version=4 if args.format == "l1a-v004" else 3,
            seed=args.seed,
            velocity=args.velocity,
            overwrite=True,
        )
    options.say(
        f"wrote {path} (3N {scene.left.shape[1]}x{scene.left.shape[0]}, "
        f"3B {scene.right.shape[1]}x{scene.right.shape[0]}), truth_dem.tif, truth_ortho.tif, "
        "points.csv"
    )
    return 0


def _run_strip(args, dem, inputs) -> int:
    """``--granules N``: consecutive granules of one pass
    (:mod:`stereodem.sensor.simulation.aster_strip`)."""
    from stereodem.sensor.simulation.aster_strip import simulate_strip, write_strip

    from .outlock import output_folder

    version = 4 if args.format == "l1a-v004" else 3
    log.info("simulating %d granules of %dx%d", args.granules, *args.size)
    strip = simulate_strip(
        args.granules,
        size=tuple(args.size),
        right_size=tuple(args.right_size) if args.right_size else None,
        seed=args.seed,
        noise=args.noise,
        dem=dem,
        texture=args.texture,
        velocity=args.velocity,
        version=version,
    )
    with output_folder(args.out, PRODUCTS, overwrite=args.overwrite, inputs=inputs) as out:
        paths = write_strip(strip, out, overwrite=True, version=version)
    for p, first in zip(paths, strip.first_lines):
        options.say(f"wrote {p} (3N lines {first}..{first + strip.heights[0] - 1} of the pass)")
    options.say(
        f"  overlap {strip.heights[0] - strip.advance} 3N lines between granules; truth_dem.tif, "
        f"truth_ortho.tif, points.csv, strip.json"
    )
    return 0
