"""stereodem demo: the whole job on the built-in example, nothing to download.

Simulates an ASTER-like 3N/3B pair from the bundled real SRTM DEM and Landsat texture,
writes it as an ASTER L1A V004 granule (HDF-EOS2, the format NASA distributes), then runs the
whole job on that granule (the real input path: granule reader, radiometric correction,
sensor models from the granule's lattice) with the true DEM as the reference and the
simulator's check points, and prints where the products are and the headline accuracy.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from stereodem.core.errors import InputError

from . import options
from .commands import help_line

EXAMPLES = """examples:
  stereodem demo -o demo_out
  stereodem demo -o demo_out --size 800 800 --workers 2 --overwrite
"""

CONFIG = """# written by 'stereodem demo'; run again with: stereodem run {cfg} --resume
# (--resume reuses the demo's tiles and replaces its products; after editing the stereo
# settings: --overwrite, or another [output] dir)
[inputs]
left = "scene/{granule}"           # an ASTER L1A granule: its 3N/3B bands are the pair
seed_dem = "{seed}"
seed_dem_vertical = "geoid"
reference_dem = "scene/truth_dem.tif"
reference_vertical = "ellipsoid"
checkpoints = "scene/points.csv"

[output]
dir = "result"

[rectification]
tile_size = 512

[matching]
matcher = "ncc"

[ortho]
both = true
fill_dem = "{seed}"                # 3B sees beyond the stereo DEM: the SRTM fills those cells
fill_dem_vertical = "geoid"

[assess]
coregister = true

[run]
tile_timeout = 600
"""


def add_parser(sub):
    p = sub.add_parser(
        "demo",
        help=help_line("demo"),
        description=__doc__,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument(
        "--size",
        nargs=2,
        type=int,
        default=[600, 600],
        metavar=("W", "H"),
        help="3N size in pixels, width a multiple of 10 (default 600 600; 3B in the real ratio)",
    )
    p.add_argument("--seed", type=int, default=0, help="simulator random seed (default 0)")
    p.add_argument("--noise", type=float, default=1.0, help="image noise sigma, DN (default 1.0)")
    p.add_argument("--workers", type=int, help="worker processes (default: all cores)")
    options.add_overwrite(p)
    p.set_defaults(run=run)
    return p


def run(args) -> int:
    """Run ``stereodem demo`` in its locked output folder."""
    from .outlock import output_folder

    with output_folder(args.out, overwrite=args.overwrite) as out:
        return _demo(args, out)


def _demo(args, out) -> int:
    from stereodem.sensor.simulation.aster_granule import granule_right_size, write_granule_scene
    from stereodem.sensor.simulation.simulate import simulate_scene

    from .config import load_config
    from .pipeline.job import run as run_pipeline
    from .run_cli import progress_factory, summarize

    t0 = time.perf_counter()
    if args.size[0] % 10:
        raise InputError(
            f"--size width {args.size[0]} must be a multiple of 10 (an ASTER granule "
            "has 11 lattice columns)"
        )
    scene = simulate_scene(
        "aster",
        size=tuple(args.size),
        right_size=granule_right_size(args.size),
        seed=args.seed,
        noise=args.noise,
    )
    granule = write_granule_scene(scene, out / "scene", version=4, seed=args.seed, overwrite=True)
    options.say(
        f"simulated ASTER L1A granule (3N {args.size[0]}x{args.size[1]}, 3B "
        f"{scene.right.shape[1]}x{scene.right.shape[0]}) in {time.perf_counter() - t0:.1f} s: "
        f"{granule}"
    )
    cfg_path = Path(out) / "demo.toml"
    from stereodem.core.dem import DEM

    seed = DEM.bundled().path  # the same real SRTM the scene was made from, as a seed
    cfg_path.write_text(CONFIG.format(cfg=cfg_path, seed=seed, granule=granule.name))
    cfg = load_config(cfg_path, workers=args.workers, overwrite=True)
    info = run_pipeline(cfg, progress_factory=progress_factory(args))
    summarize(info)
    options.say(f"end to end {time.perf_counter() - t0:.1f} s")
    return 0
