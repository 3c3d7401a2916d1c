"""The fast first-order map path (issue #17 speed target) against exact per-cell propagation.

The maps interpolate terrain-free fields from a coarse (x, y, h) lattice and apply each cell's
DEM height and slope in float32 (:mod:`stereodem.ortho.uncertainty.first_order_maps`). Here
every checked cell is also propagated exactly (:func:`propagation.first_order` with the DEM:
the model's Jacobians at the cell's own ground point, the DEM slope in ``A``), on rough terrain
with slopes up to ~0.5 and a void, for an RPC image and a frame camera.

Stated tolerance: 1e-3 relative on σ_E, σ_N, σ_horizontal and CE90 at every valid cell (the
per-map ``interpolation_error`` must be below it too), the same valid cells except at most a
thin border, the same dominant source wherever the exact leader leads by more than 1 % of the
variance, and whole-image shares within 1e-3.
"""

import os

import cv2
import numpy as np
import pytest
from affine import Affine
from scipy import ndimage

from stereodem.core.dem import DEM
from stereodem.core.errors import AccuracyError
from stereodem.ortho.grid import grid_for_model
from stereodem.ortho.uncertainty import first_order_maps as F
from stereodem.ortho.uncertainty import propagation as P
from stereodem.ortho.uncertainty.maps import ortho_uncertainty_maps
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import frame_pair

TOL = 1e-3


def _rough_dem(model, h0, *, step=5e-5, void=True):
    """An ellipsoidal DEM under ``model``: hills of ±60 m over ~150 m wavelengths (slopes up
    to ~0.5) on a tilted plane, with a void of 12 × 12 posts."""
    lon, lat = model.footprint(h0)
    w, s, e, n = lon.min() - 0.002, lat.min() - 0.002, lon.max() + 0.002, lat.max() + 0.002
    tr = Affine(step, 0, w, 0, -step, n)
    nx, ny = int((e - w) / step), int((n - s) / step)
    X, Y = tr @ np.meshgrid(np.arange(nx) + 0.5, np.arange(ny) + 0.5)
    Z = (
        h0
        + 60.0 * np.sin((X - w) / 0.0011) * np.cos((Y - s) / 0.0013)
        + 4e3 * (X - w)
        - 2e3 * (Y - s)
    )
    if void:
        k = max(12, nx // 40)
        Z[ny // 2 : ny // 2 + k, nx // 3 : nx // 3 + k] = np.nan
    return DEM(Z.astype(np.float32), tr, "EPSG:4326", "ellipsoid")


@pytest.fixture(scope="module")
def rpc_case(data_dir):
    rpc = RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")
    names = ["col_shift", "row_shift", "col_drift_col", "row_drift_row", "dem_height"]
    sig = [0.7, 0.4, 2e-4, 1e-4, 6.0]
    return rpc, _rough_dem(rpc, 2300.0), names, np.diag(np.square(sig)), 2.0


@pytest.fixture(scope="module")
def frame_case():
    cam, _ = frame_pair(32.8, 39.9, 1000.0, (512, 512))
    names = ["roll", "pitch", "yaw", "x", "y", "z", "imaging_time", "dem_height"]
    sig = np.array([2e-5, 2e-5, 5e-5, 5.0, 5.0, 5.0, 1e-3, 5.0])
    D = np.diag(sig**2)
    D[0, 1] = D[1, 0] = 0.5 * sig[0] * sig[1]  # correlated roll/pitch
    return cam, _rough_dem(cam, 1000.0, step=2e-4), names, D, None


def _exact(model, dem, grid, names, D, every):
    """Exact first-order propagation at every ``every``-th cell: (rows, cols, PointUncertainty)."""
    m = P.adjustable_model(model)
    r, c = np.mgrid[0 : grid.height : every, 0 : grid.width : every]
    r, c = r.ravel(), c.ravel()
    lon, lat = grid.lonlat(c.astype(float), r.astype(float))
    h = dem.sample(lon, lat)
    col, row = (np.asarray(a) for a in m.project(lon, lat, np.where(np.isfinite(h), h, 0.0)))
    inside = (
        np.isfinite(h)
        & (col >= -0.5)
        & (row >= -0.5)
        & (col <= m.width - 0.5)
        & (row <= m.height - 0.5)
    )
    pu = P.first_order(m, lon[inside], lat[inside], h[inside], names, D, grid.crs, dem=dem)
    return r, c, inside, pu


def _near_void(dem, grid, r, c, posts=2):
    lon, lat = grid.lonlat(c.astype(float), r.astype(float))
    dc, dr, _ = P.dem_pixel_jacobian(dem, lon, lat, grid.crs)
    near = ndimage.binary_dilation(np.isnan(dem.heights), iterations=posts + 1)
    return near[
        np.clip(np.floor(dr).astype(int), 0, dem.shape[0] - 1),
        np.clip(np.floor(dc).astype(int), 0, dem.shape[1] - 1),
    ]


@pytest.mark.parametrize("case", ["rpc_case", pytest.param("frame_case", marks=pytest.mark.slow)])
def test_fast_maps_agree_with_exact_per_cell_propagation(case, request):
    model, dem, names, D, res = request.getfixturevalue(case)
    grid = grid_for_model(model, dem, res=res)
    maps = ortho_uncertainty_maps(model, dem, grid, D, names, threads=2)
    r, c, inside, pu = _exact(model, dem, grid, names, D, every=2)
    assert inside.sum() > 3000
    assert _near_void(dem, grid, r[inside], c[inside]).sum() > 5  # the void is seen

    # the same valid cells, except a border of the footprint (image-position rounding)
    valid = np.isfinite(maps.sigma_horizontal[r, c])
    assert (valid != inside).mean() < 0.005
    # values: all cells but those within 2 posts of a void, where the slope rule (no slope
    # next to a void) is discontinuous in position and a cell may change side
    both = valid[inside] & ~_near_void(dem, grid, r[inside], c[inside])
    rr, cc = r[inside][both], c[inside][both]
    rel = lambda got, ref: np.max(np.abs(got.astype(float) / ref - 1))
    assert rel(maps.sigma_east[rr, cc], pu.sigma_east[both]) < TOL
    assert rel(maps.sigma_north[rr, cc], pu.sigma_north[both]) < TOL
    assert rel(maps.sigma_horizontal[rr, cc], pu.sigma_horizontal[both]) < TOL
    sub = slice(None, None, 7)  # the exact CE90 is slow: every 7th cell
    assert rel(maps.ce90[rr, cc][sub], P.ce90(pu.cov[both][sub])) < TOL
    assert maps.interpolation_error < TOL

    # dominant source wherever the exact leader is clear
    S = np.stack([pu.shares[n] for n in names], -1)[both]
    top2 = np.sort(S, -1)[:, -2:]
    clear = top2[:, 1] - top2[:, 0] > 0.01
    assert clear.sum() > 1000
    assert np.array_equal(maps.dominant[rr, cc][clear], np.argmax(S, -1)[clear])
    # whole-image shares: variance-weighted mean of the exact per-cell shares
    V = pu.sigma_horizontal[both] ** 2
    exact_shares = (S * V[:, None]).sum(0) / V.sum()
    for k, n in enumerate(names):
        assert maps.shares[n] == pytest.approx(exact_shares[k], abs=TOL)
    # the terrain matters here: σ on the slopes differs from the flat-terrain σ
    flat = P.first_order(
        P.adjustable_model(model),
        *grid.lonlat(cc.astype(float), rr.astype(float)),
        dem.sample(*grid.lonlat(cc.astype(float), rr.astype(float))),
        names,
        D,
        grid.crs,
    )
    assert np.max(np.abs(flat.sigma_horizontal / pu.sigma_horizontal[both] - 1)) > 20 * TOL


def test_fast_maps_source_maps_sum_to_one(rpc_case):
    model, dem, names, D, _ = rpc_case
    grid = grid_for_model(model, dem, res=12.0)
    maps = ortho_uncertainty_maps(
        model,
        dem,
        grid,
        D,
        names,
        source_maps=True,
        groups={"image": names[:4], "dem": ["dem_height"]},
    )
    total = maps.source_maps["image"] + maps.source_maps["dem"]
    ok = np.isfinite(maps.sigma_horizontal)
    assert ok.mean() > 0.5
    assert np.all(np.isnan(total[~ok]))
    assert np.max(np.abs(total[ok] - 1)) < TOL
    dom_dem = maps.dominant[ok] == 1
    assert np.array_equal(dom_dem, maps.source_maps["dem"][ok] > 0.5)


def test_numpy_dem_sampling_fallback_matches_cv2_remap(rpc_case, monkeypatch):
    """DEMs larger than OpenCV's remap limit are sampled with numpy (exact bilinear); both
    samplings give the same maps: 1e-4 relative with OpenCV >= 5; OpenCV 4 rounds remap
    positions to 1/32 post (INTER_BITS), measured 6.6e-4 relative with 4.8 and 4.10."""
    model, dem, names, D, _ = rpc_case
    grid = grid_for_model(model, dem, res=6.0)
    a = ortho_uncertainty_maps(model, dem, grid, D, names)
    monkeypatch.setattr(F, "_REMAP_MAX", 0)
    b = ortho_uncertainty_maps(model, dem, grid, D, names)
    ok = np.isfinite(a.sigma_horizontal) & np.isfinite(b.sigma_horizontal)
    assert ok.mean() > 0.5
    assert (np.isfinite(a.sigma_horizontal) != np.isfinite(b.sigma_horizontal)).mean() < 0.002
    tol = 1e-4 if int(cv2.__version__.split(".")[0]) >= 5 else 1e-3
    assert np.max(np.abs(a.sigma_horizontal[ok] / b.sigma_horizontal[ok] - 1)) < tol
    assert b.interpolation_error < TOL


def test_fast_maps_do_not_depend_on_the_thread_count(rpc_case):
    model, dem, names, D, _ = rpc_case
    grid = grid_for_model(model, dem, res=4.0)
    a = ortho_uncertainty_maps(model, dem, grid, D, names, threads=1)
    b = ortho_uncertainty_maps(model, dem, grid, D, names, threads=3)
    assert np.isfinite(a.sigma_horizontal).mean() > 0.5
    for x, y in (
        (a.sigma_east, b.sigma_east),
        (a.sigma_north, b.sigma_north),
        (a.ce90, b.ce90),
        (a.dominant, b.dominant),
    ):
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
    assert a.shares == pytest.approx(b.shares, rel=1e-12)


def test_fast_maps_default_to_the_process_thread_budget(rpc_case, monkeypatch):
    """Without ``threads`` the first-order blocks ran on os.cpu_count() threads, whatever the
    process's budget (a library caller's pin_threads, --workers): now on the budget
    (core.blocks.default_threads, OpenCV's pinned setting)."""
    model, dem, names, D, _ = rpc_case
    grid = grid_for_model(model, dem, res=8.0)
    pools = []

    class Recording(F.ThreadPoolExecutor):
        def __init__(self, n, *a, **k):
            pools.append(n)
            super().__init__(n, *a, **k)

    monkeypatch.setattr(F, "ThreadPoolExecutor", Recording)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    before = cv2.getNumThreads()
    try:
        maps = {}
        for budget in (1, 3):
            cv2.setNumThreads(budget)
            pools.clear()
            maps[budget] = ortho_uncertainty_maps(model, dem, grid, D, names)
            assert pools == ([] if budget == 1 else [budget]), (budget, pools)
    finally:
        cv2.setNumThreads(before)
    assert np.array_equal(maps[1].sigma_east, maps[3].sigma_east, equal_nan=True)


@pytest.fixture(scope="module")
def holed_case(data_dir):
    """The Pleiades RPC image over a smooth tilted surface, as a DEM whose posts are the output
    grid's cells (10 posts of margin), with and without two holes."""
    rpc = RPCModel.from_file(data_dir / "pleiades" / "img_01_rpc.tif")
    lon, lat = rpc.footprint(2300.0)
    flat = DEM(
        np.full((3, 3), 2300.0, np.float32),
        Affine(0.01, 0, lon.min() - 0.01, 0, -0.01, lat.max() + 0.01),
        "EPSG:4326",
        "ellipsoid",
    )
    grid = grid_for_model(rpc, flat, res=4.0)
    m = 10
    t = grid.transform @ Affine.translation(-m, -m)
    r, c = np.mgrid[0 : grid.height + 2 * m, 0 : grid.width + 2 * m]
    z = 2300.0 + 1.2 * c + 0.8 * r + 0.004 * (c - 60.0) ** 2  # slopes ~0.2..0.5
    whole = DEM(z.astype(np.float32), t, grid.crs, "ellipsoid")
    holed = z.copy()
    holed[m + 30 : m + 42, m + 20 : m + 35] = np.nan
    holed[m + 70 : m + 73, m + 60 : m + 62] = np.nan
    holes = DEM(holed.astype(np.float32), t, grid.crs, "ellipsoid")
    names = ["col_shift", "row_shift", "dem_height"]
    return rpc, grid, whole, holes, names, np.diag([0.5**2, 0.5**2, 20.0**2]), m


@pytest.mark.parametrize("method", ["first-order", "monte-carlo"])
def test_dem_holes_leave_no_ring_of_nodata(holed_case, method):
    """Every cell with a DEM height gets an uncertainty, the holes' cells stay nodata (a ring
    of nodata was left around each hole: the first-order maps sampled the DEM with cv2.remap,
    whose neighbour of no weight made a NaN; the sampling methods blanked every lattice square
    touching a node in a hole), and at a hole's rim the value is close to the one without the
    hole (the slope there is one-sided, as numpy.gradient at a border; it was taken as flat)."""
    rpc, grid, whole, holes, names, D, m = holed_case
    kw = dict(samples=40, step=8) if method != "first-order" else {}  # one lattice for both
    ref = ortho_uncertainty_maps(rpc, whole, grid, D, names, method, **kw).sigma_horizontal
    got = ortho_uncertainty_maps(rpc, holes, grid, D, names, method, **kw).sigma_horizontal
    in_image = np.isfinite(ref)
    dem_valid = np.isfinite(holes.heights[m:-m, m:-m])
    assert in_image.mean() > 0.5 and (~dem_valid & in_image).sum() == 12 * 15 + 3 * 2
    np.testing.assert_array_equal(np.isfinite(got), dem_valid & in_image)
    rim = ndimage.binary_dilation(~dem_valid, iterations=2) & dem_valid & in_image
    assert rim.sum() > 50
    rel = np.abs(got[rim] / ref[rim] - 1)
    assert rel.max() < 0.02, rel.max()
    # and the dem_height term matters at the rim: a flat rim was off by more than that
    assert (
        ortho_uncertainty_maps(rpc, whole, grid, D[2:, 2:], names[2:]).sigma_horizontal[rim].std()
        > 0
    )


def test_dem_gradient_is_one_sided_beside_voids():
    """numpy.gradient's rule at a border, at a void's edge too; NaN only on the voids."""
    z = np.add.outer(0.5 * np.arange(6.0), 2.0 * np.arange(7.0) ** 2)
    z[2, 3] = np.nan
    dem = DEM(z.astype(np.float32), Affine(1, 0, 0, 0, -1, 0), "EPSG:32740")
    gc, gr = P.dem_gradient_arrays(dem)
    assert np.isnan(gc[2, 3]) and np.isnan(gr[2, 3])
    assert np.isfinite(gc).sum() == z.size - 1 and np.isfinite(gr).sum() == z.size - 1
    assert gc[2, 2] == pytest.approx(z[2, 2] - z[2, 1])  # one-sided, backward
    assert gc[2, 4] == pytest.approx(z[2, 5] - z[2, 4])  # one-sided, forward
    assert gr[1, 3] == pytest.approx(z[1, 3] - z[0, 3]) and gr[3, 3] == pytest.approx(0.5)
    full = np.gradient(np.where(np.isnan(z), 0.0, z))
    assert gc[0, 0] == pytest.approx(full[1][0, 0]) and gr[5, 6] == pytest.approx(full[0][5, 6])


def test_single_input_with_a_vanishing_component_is_right_on_every_cell():
    """One input moving the ground along one map axis (a frame camera's yaw over rough
    terrain): the other component nearly vanishes (~1e-5 of σ_horizontal). The maps formed
    ``M Σ₀ Mᵀ`` from float32 covariance entries and interpolated ``Σ₀`` itself, so that
    component was rounding noise and a turning direction's spurious minor axis: off by 0.03
    of σ_horizontal on the cells (the documented measure, a component relative to
    max(σ_component, 0.01 σ_horizontal)), with a warning, "0.0063 exceeds 0.001", and the maps
    returned. Now the lattice carries Σ₀'s square root: the check cells within the tolerance,
    every cell within twice it (the check cells are a sample of 400)."""
    cam, _ = frame_pair(32.8, 39.9, 1000.0, (256, 256))
    dem = _rough_dem(cam, 1000.0, step=2e-4, void=False)
    names, D = ["yaw"], np.diag([1e-10])
    grid = grid_for_model(cam, dem)
    maps = ortho_uncertainty_maps(cam, dem, grid, D, names, threads=1)
    r, c, inside, pu = _exact(cam, dem, grid, names, D, every=2)
    exact = np.stack([pu.sigma_east, pu.sigma_north], -1)
    assert np.min(exact.min(1) / pu.sigma_horizontal) < 1e-4  # the vanishing component
    got = np.stack([maps.sigma_east[r, c], maps.sigma_north[r, c]], -1)[inside].astype(float)
    ok = np.all(np.isfinite(got), -1)
    assert ok.mean() > 0.99
    assert F.relative_error(got[ok], exact[ok]) < 2 * TOL
    assert maps.interpolation_error < TOL


def test_maps_beyond_the_tolerance_are_refused_not_returned(rpc_case, monkeypatch, caplog):
    """A measured error above the tolerance on the finest lattice was a warning and the maps
    were returned (the command wrote them and exited 0): now an AccuracyError; with the
    caller's own ``step`` it stays a warning."""
    model, dem, names, D, _ = rpc_case
    grid = grid_for_model(model, dem, res=12.0)
    with pytest.raises(AccuracyError, match=r"exceeds the tolerance 1e-09 on a lattice of 4"):
        ortho_uncertainty_maps(model, dem, grid, D, names, tolerance=1e-9)
    with caplog.at_level("WARNING"):
        maps = ortho_uncertainty_maps(model, dem, grid, D, names, tolerance=1e-9, step=64)
    assert maps.step == 64 and "fixed by the caller" in caplog.text


def _gradient_by_definition(z, axis):
    """The gradient rule written out cell by cell: central where both steps are finite, else
    the finite one, else 0; NaN on the voids."""
    z = np.moveaxis(np.asarray(z, np.float64), axis, 0)
    fwd, bwd = np.full(z.shape, np.nan), np.full(z.shape, np.nan)
    if z.shape[0] > 1:
        fwd[:-1] = bwd[1:] = z[1:] - z[:-1]
    f_ok, b_ok = np.isfinite(fwd), np.isfinite(bwd)
    g = np.where(f_ok & b_ok, 0.5 * (fwd + bwd), np.where(f_ok, fwd, np.where(b_ok, bwd, 0.0)))
    g[~np.isfinite(z)] = np.nan
    return np.moveaxis(g, 0, axis)


@pytest.mark.parametrize("shape", [(1, 5), (5, 1), (2, 2), (7, 9), (60, 40)])
@pytest.mark.parametrize("voids", [0.0, 0.05, 0.5, 1.0])
def test_axis_gradient_is_the_rule_bit_for_bit(shape, voids):
    """axis_gradient mends only the rims of voids by index (4.5x faster on a 2534 x 2382 DEM
    than the rule's full-size passes): the same bits as the rule, on any grid and share of
    voids, along both axes."""
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    z = rng.normal(0, 100, shape).astype(np.float32)
    z[rng.random(shape) < voids] = np.nan
    for axis in (0, 1):
        np.testing.assert_array_equal(P.axis_gradient(z, axis), _gradient_by_definition(z, axis))
