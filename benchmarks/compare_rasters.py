"""Compare every GeoTIFF of two output trees bit for bit (pixels, transform, CRS, nodata, tags).

Usage: python benchmarks/compare_rasters.py BEFORE_DIR AFTER_DIR
Prints one line per raster and exits 1 when any differs (issue #23: renovation without changes
to the products).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
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


def _what_differs(a, b, ma, mb) -> str:
    """Empty when all is equal, else what differs: pixels (how many, largest difference) and
    which metadata (tags added, removed or changed, by name)."""
    out = []
    if a.shape != b.shape or a.dtype != b.dtype:
        out.append(f"shape/type {a.shape} {a.dtype} -> {b.shape} {b.dtype}")
    elif a.tobytes() != b.tobytes():
        x, y = a.astype(float), b.astype(float)
        diff = ~((x == y) | (np.isnan(x) & np.isnan(y)))
        both = np.isfinite(x) & np.isfinite(y)
        big = float(np.abs(x - y)[both & diff].max()) if (both & diff).any() else 0.0
        out.append(f"{int(diff.sum())} pixels (max |difference| {big:.4g})")
    names = ("transform", "crs", "nodata", "dtypes", "tags", "blockxsize")
    for name, u, v in zip(names, ma, mb):
        if u == v:
            continue
        if name == "tags":
            added = sorted(set(v) - set(u))
            removed = sorted(set(u) - set(v))
            changed = sorted(k for k in set(u) & set(v) if u[k] != v[k])
            out.append(f"tags added {added} removed {removed} changed {changed}")
        else:
            out.append(name)
    return (": " + "; ".join(out)) if out else ""


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
        pixels = a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
        same = pixels and ma == mb
        print(f"{'same    ' if same else 'DIFFERS '} {rel}{_what_differs(a, b, ma, mb)}")
        bad += not same
    print(f"{len(paths) - bad}/{len(paths)} rasters bit-identical")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
