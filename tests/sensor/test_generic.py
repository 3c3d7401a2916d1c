"""Generic orthorectification models fitted to GCPs (Ok 2005, Ch. 3.1.3 and Ch. 6)."""

import numpy as np
import pytest

from stereodem.core import geodesy
from stereodem.core.errors import InputError
from stereodem.sensor.estimation import regularize
from stereodem.sensor.io.gcps import read_gcps, write_gcps
from stereodem.sensor.models.base import SensorModel
from stereodem.sensor.models.generic import (
    MODEL_NAMES,
    FitReport,
    GenericModel,
    fit_model,
    minimum_gcps,
    n_parameters,
)

LON0, LAT0 = 32.8, 39.9  # Ankara, UTM 36N, as in the Ok thesis
CRS = geodesy.utm_crs(LON0, LAT0)
E0, N0 = (float(v) for v in geodesy.lonlat_to_crs(LON0, LAT0, CRS))
GSD = 15.0
SIZE = 4000  # image is SIZE x SIZE pixels, 60 km x 60 km


class MapFunctionCamera(SensorModel):
    """A 'sensor' whose ground->image mapping is a given function of UTM (E, N, h)."""

    def __init__(self, fn):
        self.fn = fn
        self.width = self.height = SIZE

    def project(self, lon, lat, h):
        E, N = geodesy.lonlat_to_crs(lon, lat, CRS)
        return self.fn(np.asarray(E), np.asarray(N), np.asarray(h, float))


class PushbroomLike(SensorModel):
    """Analytic pushbroom in the map frame: one central projection per row (line).

    The camera flies north at 705 km with a quadratic drift across track and in height, a
    small roll, and looks back by ``tilt`` along track; row = time / line time, col = central
    projection across track within the scan plane of that time.
    """

    def __init__(self, *, tilt_deg=0.0, roll_deg=8.55, drift=5e-7, hdrift=3e-6):
        self.width = self.height = SIZE
        self.H = 705e3
        self.f = self.H / GSD
        self.tilt = np.radians(tilt_deg)
        self.roll = np.radians(roll_deg)
        self.drift, self.hdrift = drift, hdrift
        self.N_start = N0 - SIZE / 2 * GSD + np.tan(self.tilt) * self.H

    def _camera(self, r):
        s = r - SIZE / 2
        return (
            E0 + self.drift * s**2 * GSD,
            self.N_start + r * GSD,
            self.H + self.hdrift * s**2 * GSD,
        )

    def project(self, lon, lat, h):
        E, N = geodesy.lonlat_to_crs(lon, lat, CRS)
        E, N, h = np.asarray(E), np.asarray(N), np.asarray(h, float)
        ct, st = np.cos(self.tilt), np.sin(self.tilt)
        r = (N - self.N_start) / GSD
        for _ in range(8):  # scan plane through the camera at time r: ct dN - st dh = 0
            Ec, Nc, Hc = self._camera(r)
            g = ct * (N - Nc) - st * (h - Hc)
            dg = -ct * GSD + st * 2 * self.hdrift * (r - SIZE / 2) * GSD
            r = r - g / dg
        Ec, Nc, Hc = self._camera(r)
        depth = -st * (N - Nc) - ct * (h - Hc)
        alpha = np.arctan2(E - Ec, depth) - self.roll
        return SIZE / 2 + self.f * np.tan(alpha), r


def ground_points(n, rng, *, hmax=3000.0, margin=0.45):
    """Random points over the scene, heights uniform in [0, hmax] m (rugged terrain)."""
    E = E0 + rng.uniform(-margin, margin, n) * SIZE * GSD
    N = N0 + rng.uniform(-margin, margin, n) * SIZE * GSD
    lon, lat = geodesy.crs_to_lonlat(E, N, CRS)
    return np.asarray(lon), np.asarray(lat), rng.uniform(0.0, hmax, n)


def observe(camera, n, rng, *, noise=0.0, hmax=3000.0):
    lon, lat, h = ground_points(n, rng, hmax=hmax)
    col, row = camera.project(lon, lat, h)
    return lon, lat, h, col + rng.normal(0, noise, n), row + rng.normal(0, noise, n)


# ----------------------------------------------------------- geometries in each function class
def _en(E, N):
    return (E - E0) / 30e3, (N - N0) / 30e3


def _exact_geometries():
    """Ground->image functions lying exactly in each model's class (pixels)."""

    def poly2d(k):
        def fn(E, N, h):
            e, n = _en(E, N)
            c = 2000 + 1950 * e + 60 * n
            r = 2000 - 40 * e + 2010 * n
            if k >= 2:
                c, r = (
                    c + 15 * e * e - 9 * e * n + 4 * n * n,
                    r + 7 * e * e + 11 * e * n - 6 * n * n,
                )
            if k >= 3:
                c, r = c + 3 * e**3 - 2 * e * e * n + 5 * n**3, r - 4 * e**3 + e * n * n + 2 * n**3
            return c, r

        return fn

    def poly3d(k):
        base = poly2d(k)

        def fn(E, N, h):
            e, n = _en(E, N)
            z = (h - 1500) / 1500
            c, r = base(E, N, h)
            c, r = c + 8 * z, r - 3 * z
            if k >= 2:
                c, r = c + 2 * z * z + 5 * e * z, r - 1.5 * z * z + 4 * n * z
            if k >= 3:
                c, r = c + z**3 + 2 * e * n * z - z * z * n, r - 0.7 * z**3 + 3 * e * e * z
            return c, r

        return fn

    def relief(k):
        base = poly2d(k)

        def fn(E, N, h):
            c, r = base(E, N, h)
            z = h / 1000.0
            return c * (1 + 0.004 * z) + 6 * z, r * (1 - 0.002 * z) - 2 * z

        return fn

    def projective(E, N, h):
        e, n = _en(E, N)
        w = 1 + 0.03 * e - 0.02 * n
        return (2000 + 1900 * e + 70 * n) / w, (2000 - 50 * e + 2000 * n) / w

    def projective_pushbroom(E, N, h):
        e, n = _en(E, N)
        return (2000 + 1900 * e + 70 * n) / (1 + 0.03 * e - 0.02 * n), 2000 - 50 * e + 2000 * n

    # a frame pinhole in the map frame: camera 6 km above the scene, tilted
    om, ph, ka = np.radians([4.0, -6.0, 20.0])
    Rx = np.array([[1, 0, 0], [0, np.cos(om), -np.sin(om)], [0, np.sin(om), np.cos(om)]])
    Ry = np.array([[np.cos(ph), 0, np.sin(ph)], [0, 1, 0], [-np.sin(ph), 0, np.cos(ph)]])
    Rz = np.array([[np.cos(ka), -np.sin(ka), 0], [np.sin(ka), np.cos(ka), 0], [0, 0, 1]])
    R = Rz @ Ry @ Rx
    C = np.array([E0 + 300.0, N0 - 200.0, 40e3])

    def dlt(E, N, h):
        d = np.stack([E - C[0], N - C[1], h - C[2]], -1) @ R  # camera frame (rows of R^T)
        f = 40e3 / GSD
        return 2000 + f * d[..., 0] / -d[..., 2], 2000 - f * d[..., 1] / -d[..., 2]

    def edlt(E, N, h):
        u, v = dlt(E, N, h)
        a12, a13 = 2e-7, -3e-7  # per pixel: x = u + a12 x y, y = v + a13 y^2
        y = 2 * v / (1 + np.sqrt(1 - 4 * a13 * v))
        return u / (1 - a12 * y), y

    def rational(k):
        def fn(E, N, h):
            e, n = _en(E, N)
            z = (h - 1500) / 1500
            P = [
                1,
                e,
                n,
                z,
                e * e,
                n * n,
                z * z,
                e * n,
                e * z,
                n * z,
                e**3,
                n**3,
                z**3,
                e * e * n,
                e * e * z,
                n * n * e,
                n * n * z,
                z * z * e,
                z * z * n,
                e * n * z,
            ][: {1: 4, 2: 10, 3: 20}[k]]
            P = np.stack(np.broadcast_arrays(*P), -1)
            m = P.shape[-1]
            rng = np.random.default_rng(k)
            a = np.r_[2000, 1900, 60, 25, rng.normal(0, 8, m - 4)]
            b = np.r_[2000, -40, 2000, -10, rng.normal(0, 8, m - 4)]
            dc = np.r_[1.0, 0.02, -0.01, 0.005, rng.normal(0, 0.004, m - 4)]
            dr = np.r_[1.0, -0.015, 0.01, 0.003, rng.normal(0, 0.004, m - 4)]
            return (P @ a) / (P @ dc), (P @ b) / (P @ dr)

        return fn

    g = {f"poly2d-{k}": poly2d(k) for k in (1, 2, 3)}
    g.update({f"poly3d-{k}": poly3d(k) for k in (1, 2, 3)})
    g.update(
        {
            "relief-1": relief(1),
            "relief-2": relief(2),
            "projective": projective,
            "projective-pushbroom": projective_pushbroom,
            "dlt": dlt,
            "edlt": edlt,
        }
    )
    g.update({f"rational-{k}": rational(k) for k in (1, 2, 3)})
    return g


EXACT = _exact_geometries()


def test_registry_names_and_minimum_gcps():
    assert set(MODEL_NAMES) == set(EXACT)
    assert [minimum_gcps(n) for n in ("poly2d-1", "poly2d-2", "poly2d-3")] == [3, 6, 10]
    assert [minimum_gcps(n) for n in ("poly3d-1", "poly3d-2", "poly3d-3")] == [4, 10, 20]
    assert [minimum_gcps(n) for n in ("relief-1", "relief-2")] == [6, 12]
    assert [minimum_gcps(n) for n in ("projective", "projective-pushbroom", "dlt", "edlt")] == [
        4,
        5,
        6,
        7,
    ]
    # Ok: "3rd order with the denominator constants fixed to 1 has 78 unknowns, >= 39 GCPs"
    assert [minimum_gcps(f"rational-{k}") for k in (1, 2, 3)] == [7, 19, 39]
    assert n_parameters("rational-3") == 78 and n_parameters("relief-2") == 24


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_exact_recovery_of_own_function_class(name):
    rng = np.random.default_rng(7)
    cam = MapFunctionCamera(EXACT[name])
    hmax = 0.0 if name.startswith(("poly2d", "projective")) else 3000.0
    n = max(3 * minimum_gcps(name), 30)
    gcp = observe(cam, n, rng, hmax=hmax)
    chk = observe(cam, 50, rng, hmax=hmax)
    model, rep = fit_model(name, *gcp, check=chk, regularization=None)
    assert isinstance(model, GenericModel) and isinstance(model, SensorModel)
    assert rep.n_gcp == n and rep.n_check == 50 and rep.n_params == n_parameters(name)
    assert rep.gcp_rmse < 1e-6, (name, rep.gcp_rmse)
    assert rep.check_rmse < 1e-6, (name, rep.check_rmse)
    assert np.isfinite(rep.condition_number) and rep.condition_number >= 1.0


@pytest.fixture(scope="module")
def pushbroom_data():
    rng = np.random.default_rng(2005)
    cam = PushbroomLike()
    gcp = observe(cam, 60, rng, noise=0.2)
    chk = observe(cam, 200, rng, noise=0.2)
    return gcp, chk


@pytest.fixture(scope="module")
def pushbroom_fits(pushbroom_data):
    gcp, chk = pushbroom_data
    return {n: fit_model(n, *gcp, check=chk) for n in MODEL_NAMES}


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_localize_inverts_project(name, pushbroom_fits, pushbroom_data):
    model, _ = pushbroom_fits[name]
    lon, lat, h, _, _ = pushbroom_data[1]
    col, row = model.project(lon, lat, h)
    lon2, lat2 = model.localize(col, row, h)
    col2, row2 = model.project(lon2, lat2, h)
    assert np.all(np.isfinite(lon2))
    assert np.max(np.hypot(col2 - col, row2 - row)) < 1e-6
    assert np.max(np.abs(lon2 - lon)) < 1e-9 and np.max(np.abs(lat2 - lat)) < 1e-9
    # broadcasting and shape are kept
    c2, r2 = model.project(lon[:6].reshape(2, 3), lat[:6].reshape(2, 3), 1000.0)
    assert c2.shape == (2, 3)
    lo, la = model.localize(c2, r2, 1000.0)
    assert lo.shape == (2, 3)


def test_localize_dem_relief_iteration_runs_on_a_fitted_model(pushbroom_fits):
    class Plane:  # a DEM stand-in: 1200 m everywhere
        def sample(self, lon, lat):
            return np.full(np.shape(lon), 1200.0)

    model, _ = pushbroom_fits["rational-1"]
    res = model.localize_dem(np.array([100.0, 2000.0]), np.array([300.0, 3500.0]), Plane())
    assert np.all(res.converged)
    c, r = model.project(res.lon, res.lat, res.h)
    assert np.allclose([c, r], [[100.0, 2000.0], [300.0, 3500.0]], atol=1e-5)


def test_ranking_follows_ok_thesis(pushbroom_fits):
    """Ok's qualitative ordering: affine >> relief-1 ~ DLT > projective ~ poly-2 > poly-3 >
    RF-1 > relief-2 ~ RF-2 (notes §7.1); here relief is 0-3000 m with an 8.55 deg roll."""
    chk = {n: rep.check_rmse for n, (_, rep) in pushbroom_fits.items()}
    assert chk["poly2d-1"] > 2.0 and chk["poly2d-1"] > 0.9 * max(chk.values())
    assert chk["rational-1"] < chk["poly2d-1"] / 4
    assert chk["rational-1"] < chk["relief-1"] / 3
    assert chk["relief-2"] < chk["poly2d-2"] / 3
    for name in ("poly3d-2", "relief-2", "rational-2"):
        assert chk[name] < min(chk["poly2d-1"], chk["poly2d-2"], chk["poly2d-3"]) / 3, name
    assert chk["projective-pushbroom"] < chk["projective"]
    # Ok's DLT is the only model with a poor line (y) residual: one shared denominator
    y = {n: rep.check_rmse_y for n, (_, rep) in pushbroom_fits.items()}
    assert y["dlt"] > 3 * max(y["poly2d-1"], y["projective-pushbroom"], y["relief-2"])
    rep = pushbroom_fits["rational-2"][1]
    assert rep.regularization == "lcurve" and rep.regularization_weight > 0
    assert pushbroom_fits["poly2d-1"][1].regularization is None


def test_report_fields_and_dict(pushbroom_fits):
    _, rep = pushbroom_fits["rational-2"]
    assert isinstance(rep, FitReport)
    res = rep.gcp_residuals
    assert res.shape == (rep.n_gcp, 2)
    assert rep.gcp_rmse_x == pytest.approx(np.sqrt(np.mean(res[:, 0] ** 2)))
    assert rep.gcp_rmse == pytest.approx(np.hypot(rep.gcp_rmse_x, rep.gcp_rmse_y))
    assert rep.condition_number_regularized < rep.condition_number
    d = rep.to_dict()
    assert d["model"] == "rational-2" and d["n_params"] == 38 and "gcp_residuals" not in d
    assert d["crs"] == "EPSG:32636"
    _, rep0 = fit_model(
        "poly2d-1",
        [32.7, 32.9, 32.8, 32.75],
        [39.8, 39.85, 40.0, 39.9],
        np.zeros(4),
        [0.0, 100.0, 50.0, 20.0],
        [0.0, 10.0, 90.0, 40.0],
    )
    assert np.isnan(rep0.check_rmse) and rep0.to_dict()["check_rmse"] is None


@pytest.mark.parametrize("seed", [11, 12, 13, 14, 15])
def test_regularization_chooses_weight_from_gcps_and_helps(seed):
    """rational-2 from 25 noisy GCPs (19 unknowns per coordinate): ill-conditioned."""
    rng = np.random.default_rng(seed)
    cam = PushbroomLike(tilt_deg=10.0)
    gcp = observe(cam, 25, rng, noise=0.3)
    chk = observe(cam, 300, rng, noise=0.0)
    _, plain = fit_model("rational-2", *gcp, check=chk, regularization=None)
    assert plain.regularization is None and plain.regularization_weight is None
    for method in ("gcv", "lcurve"):
        model, rep = fit_model("rational-2", *gcp, check=chk, regularization=method)
        assert rep.regularization == method
        assert np.isfinite(rep.regularization_weight) and rep.regularization_weight > 0
        assert rep.condition_number_regularized < rep.condition_number
        # the weight does not depend on the check points
        _, alone = fit_model("rational-2", *gcp, regularization=method)
        assert alone.regularization_weight == rep.regularization_weight
        assert alone.n_check == 0
    # the L-curve corner improves the check points (GCV is not reliable here: see report)
    _, lc = fit_model("rational-2", *gcp, check=chk, regularization="lcurve")
    assert lc.check_rmse < plain.check_rmse / 2, (lc.check_rmse, plain.check_rmse)
    _, fixed = fit_model("rational-2", *gcp, check=chk, regularization=0.01)
    assert fixed.regularization == "fixed" and fixed.regularization_weight == 0.01


def test_regularize_module_on_ill_posed_problem():
    rng = np.random.default_rng(3)
    n = 40
    t = np.linspace(0, 1, 60)
    A = np.exp(-((t[:, None] - np.linspace(0, 1, n)[None]) ** 2) / 0.02)  # smoothing kernel
    x_true = np.sin(np.linspace(0, np.pi, n))
    b = A @ x_true + rng.normal(0, 1e-3, t.size)
    x_ls = regularize.tikhonov_solve(A, b, 0.0)
    errs = {}
    for name, fn in (("gcv", regularize.gcv_weight), ("lcurve", regularize.lcurve_weight)):
        lam = fn(A, b)
        s = np.linalg.svd(A, compute_uv=False)
        assert s[-1] < lam < s[0]
        x = regularize.tikhonov_solve(A, b, lam)
        np.testing.assert_allclose(
            x, np.linalg.solve(A.T @ A + lam**2 * np.eye(n), A.T @ b), rtol=1e-6, atol=1e-8
        )
        errs[name] = np.linalg.norm(x - x_true)
        assert errs[name] < np.linalg.norm(x_ls - x_true) / 10
    lams = np.logspace(-6, 1, 50)
    g = regularize.gcv_function(A, b, lams)
    assert np.argmin(g) not in (0, lams.size - 1)
    assert regularize.condition_number(A, 1.0) < regularize.condition_number(A)
    with pytest.raises(InputError):
        regularize.tikhonov_solve(A, b, -1.0)


def test_too_few_gcps_is_an_input_error():
    rng = np.random.default_rng(5)
    gcp = observe(PushbroomLike(), 30, rng)
    with pytest.raises(InputError, match=r"rational-3.*39 GCPs"):
        fit_model("rational-3", *gcp)
    with pytest.raises(InputError, match=r"dlt.*6 GCPs"):
        fit_model("dlt", *(a[:5] for a in gcp))
    with pytest.raises(InputError, match="unknown generic model"):
        fit_model("poly4d-9", *gcp)


@pytest.mark.parametrize("name", ["poly2d-1", "poly3d-1", "rational-1", "dlt"])
def test_gcps_on_one_line_are_an_input_error(name):
    """GCPs along one road (collinear on the ground): the fit used to "succeed" with an RMSE
    of 1e-6 px and a model undetermined across the line (ortho then localised the image
    corners to NaN and blamed the DEM); now an InputError saying so."""
    rng = np.random.default_rng(7)
    cam = PushbroomLike()
    t = rng.uniform(0, 1, 40)
    E, N = E0 - 20e3 + 40e3 * t, N0 - 10e3 + 25e3 * t + rng.normal(0, 1.0, 40)  # 1 m off
    lon, lat = geodesy.crs_to_lonlat(E, N, CRS)
    h = rng.uniform(0, 3000, 40)
    col, row = cam.project(lon, lat, h)
    with pytest.raises(InputError, match=f"'{name}'.*GCPs lie on one line"):
        fit_model(name, lon, lat, h, col, row)
    # the same number of points spread over the scene fits
    fit_model(name, *observe(cam, 40, rng))


def test_nan_in_gcps_or_checks_is_an_input_error():
    rng = np.random.default_rng(6)
    lon, lat, h, col, row = observe(PushbroomLike(), 30, rng)
    bad = h.copy()
    bad[4] = np.nan
    with pytest.raises(InputError, match="non-finite GCP value.*'h'"):
        fit_model("poly3d-1", lon, lat, bad, col, row)
    with pytest.raises(InputError, match="check-point"):
        fit_model("poly3d-1", lon, lat, h, col, row, check=(lon, lat, h, col, row * np.nan))
    with pytest.raises(InputError, match="different lengths"):
        fit_model("poly3d-1", lon, lat, h, col, row[:-1])


def test_gcp_csv_round_trip_and_errors(tmp_path, pushbroom_data):
    lon, lat, h, col, row = pushbroom_data[0]
    role = np.where(np.arange(lon.size) % 3 == 0, "check", "gcp")
    path = write_gcps(
        tmp_path / "points.csv",
        [f"P{i}" for i in range(lon.size)],
        lon,
        lat,
        h,
        col,
        row,
        role=role,
    )
    pts = read_gcps(path)
    assert len(pts) == lon.size and pts.id[3] == "P3"
    np.testing.assert_allclose(pts.lon, lon, atol=1e-10)
    np.testing.assert_allclose(pts.col, col, atol=1e-6)
    g, c = pts.select("gcp"), pts.select("check")
    assert len(g) + len(c) == lon.size and set(c.role) == {"check"}
    model, rep = fit_model("poly3d-2", *g.arrays(), check=c.arrays())
    assert rep.n_check == len(c)
    with pytest.raises(FileExistsError):
        write_gcps(path, ["a"], [1], [2], [3], [4], [5])

    (tmp_path / "nocol.csv").write_text("id,lon,lat,h,col\n1,32,39,100,5\n")
    with pytest.raises(InputError, match="nocol.csv: missing GCP column.*row"):
        read_gcps(tmp_path / "nocol.csv")
    (tmp_path / "nan.csv").write_text("id,lon,lat,h,col,row\n1,32,39,,5,6\n2,32,39,nan,5,6\n")
    with pytest.raises(InputError, match="nan.csv: 2 missing/NaN value.*'h'"):
        read_gcps(tmp_path / "nan.csv")
    (tmp_path / "role.csv").write_text("id,lon,lat,h,col,row,role\n1,32,39,1,5,6,tie\n")
    with pytest.raises(InputError, match="unknown role"):
        read_gcps(tmp_path / "role.csv")
    (tmp_path / "norole.csv").write_text("id,lon,lat,h,col,row\n1,32,39,1,5,6\n")
    assert read_gcps(tmp_path / "norole.csv").role.tolist() == ["gcp"]
    with pytest.raises(InputError, match="cannot read"):
        read_gcps(tmp_path / "absent.csv")
