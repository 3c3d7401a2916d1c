"""Real data example: the Pleiades 1B stereo pair of s2p's tests (La Réunion) to a 0.5 m DSM,
compared with s2p's own DSM of the same pair.

The images (about 2 MB each, (c) CNES 2013) are not bundled; point the script at the folder
holding ``img_01.tif``, ``img_02.tif`` (with RPC metadata) and ``expected_dsm.tif``:

    python examples/pleiades_pair.py ../shared/data/s2p_pleiades/pair -o pleiades_out

Equivalent command line:

    stereodem dem img_01.tif img_02.tif -o pleiades_out --res 0.5 --crs EPSG:32740 \\
        --height-range 2100 2600
    stereodem assess pleiades_out/dem.tif --ref expected_dsm.tif --ref-vertical ellipsoid \\
        -o pleiades_out/assess
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stereodem import cli


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("pair_dir", type=Path)
    ap.add_argument("-o", "--out", type=Path, default=Path("pleiades_out"))
    args = ap.parse_args(argv)
    d = args.pair_dir
    for name in ("img_01.tif", "img_02.tif", "expected_dsm.tif"):
        if not (d / name).exists():
            sys.exit(f"{d / name}: not found (see the docstring for where the pair lives)")
    rc = cli.main(
        [
            "dem",
            str(d / "img_01.tif"),
            str(d / "img_02.tif"),
            "-o",
            str(args.out),
            "--res",
            "0.5",
            "--crs",
            "EPSG:32740",
            "--height-range",
            "2100",
            "2600",
            "--overwrite",
        ]
    )
    if rc:
        return rc
    return cli.main(
        [
            "assess",
            str(args.out / "dem.tif"),
            "--ref",
            str(d / "expected_dsm.tif"),
            "--dem-vertical",
            "ellipsoid",
            "--ref-vertical",
            "ellipsoid",
            "-o",
            str(args.out / "assess"),
            "--overwrite",
        ]
    )


if __name__ == "__main__":
    sys.exit(main())
