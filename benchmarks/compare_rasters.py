"""Compare every GeoTIFF of two output trees bit for bit (pixels, transform, CRS, nodata, tags).

Usage: python benchmarks/compare_rasters.py BEFORE_DIR AFTER_DIR
Prints one line per raster and exits 1 when any differs (issue #23: renovation without changes
to the products).
"""

from __future__ import annotations

import sys
from pathlib import Path

import rasterio


def describe(path: Path):
    with rasterio.open(path) as src:
        data = src.read()
        meta = (
            src.transform,
            src.crs,
            repr(src.nodata),
            src.dtypes,
            src.tags(),
            src.profile.get("blockxsize"),
        )
    return data, meta


def main(before: str, after: str) -> int:
    before_root, after_root = Path(before), Path(after)
    bad = 0
    paths = sorted(p.relative_to(before_root) for p in before_root.rglob("*.tif"))
    if not paths:
        print(f"{before_root}: no GeoTIFF")
        return 1
    for rel in paths:
        other = after_root / rel
        if not other.exists():
            print(f"MISSING  {rel}")
            bad += 1
            continue
        a, ma = describe(before_root / rel)
        b, mb = describe(other)
        same = a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes() and ma == mb
        print(f"{'same    ' if same else 'DIFFERS '} {rel}")
        bad += not same
    print(f"{len(paths) - bad}/{len(paths)} rasters bit-identical")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
