"""RPC00B rational polynomial camera model: projection and exact localisation.

The file formats (GDAL rasters and VRTs, ``.RPB``, ``_RPC.TXT``/IKONOS, DIMAP v1/v2/v3,
DigitalGlobe XML, OSSIM ``.geom``, rpcm JSON) are read and written by
:mod:`stereodem.sensor.io.rpc_formats`.

An RPC00B model (NITF STDI-0002 RPC00B, GDAL RFC 22) maps normalised ground coordinates

    L = (lon - LONG_OFF) / LONG_SCALE,  P = (lat - LAT_OFF) / LAT_SCALE,
    H = (h - HEIGHT_OFF) / HEIGHT_SCALE

to normalised image coordinates through four cubic polynomials of 20 terms each::

    samp = SAMP_OFF + SAMP_SCALE * SAMP_NUM(L, P, H) / SAMP_DEN(L, P, H)
    line = LINE_OFF + LINE_SCALE * LINE_NUM(L, P, H) / LINE_DEN(L, P, H)

with the terms in the RPC00B order used by GDAL, rasterio and rpcm (:data:`RPC00B_TERMS`)::

    1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH², L²H, P²H, H³

Pixel convention
----------------
RPC00B puts the centre of the first pixel at (samp, line) = (0, 0): the same convention as
stereodem, so ``col = samp`` and ``row = line`` directly. GDAL's RPC transformer (and hence
``rasterio.transform.RPCTransformer``) puts (0, 0) at the top-left *corner*: GDAL pixel/line =
ours + 0.5. Pleiades/SPOT DIMAP files count pixels from 1: their LINE_OFF/SAMP_OFF are ours + 1
(the reader subtracts 1, as rpcm and GDAL do).

DIMAP naming
------------
A Pleiades/SPOT 6-7 DIMAP ``RPC_*.XML`` carries two rational models sharing one normalisation:
``Inverse_Model`` is ground -> image, i.e. the RPC00B *projection* stored here as the main
coefficients; ``Direct_Model`` is image -> ground (its SAMP_* polynomials give longitude and
its LINE_* polynomials latitude, as functions of normalised (col, row, H) in the (L, P, H)
slots). The direct model is kept as :attr:`RPCModel.loc_coeffs` and used only as the initial
guess of the exact Newton localisation.
"""

from __future__ import annotations

import math
import re
import warnings

import numpy as np
from rasterio.rpc import RPC

from stereodem.core.errors import RPCError, where
from stereodem.sensor.models.base import SensorModel, broadcast_coordinates

#: RPC00B term order (L = normalised longitude, P = latitude, H = height).
RPC00B_TERMS = (
    "1",
    "L",
    "P",
    "H",
    "LP",
    "LH",
    "PH",
    "L2",
    "P2",
    "H2",
    "PLH",
    "L3",
    "LP2",
    "LH2",
    "L2P",
    "P3",
    "PH2",
    "L2H",
    "P2H",
    "H3",
)

#: Exponents (of L, P, H) of the 20 RPC00B terms.
EXPONENTS = np.array(
    [
        (0, 0, 0),
        (1, 0, 0),
        (0, 1, 0),
        (0, 0, 1),
        (1, 1, 0),
        (1, 0, 1),
        (0, 1, 1),
        (2, 0, 0),
        (0, 2, 0),
        (0, 0, 2),
        (1, 1, 1),
        (3, 0, 0),
        (1, 2, 0),
        (1, 0, 2),
        (2, 1, 0),
        (0, 3, 0),
        (0, 1, 2),
        (2, 0, 1),
        (0, 2, 1),
        (0, 0, 3),
    ],
    dtype=int,
)

#: Scalar RPC keys (GDAL RPC metadata domain names).
SCALAR_KEYS = (
    "LINE_OFF",
    "SAMP_OFF",
    "LAT_OFF",
    "LONG_OFF",
    "HEIGHT_OFF",
    "LINE_SCALE",
    "SAMP_SCALE",
    "LAT_SCALE",
    "LONG_SCALE",
    "HEIGHT_SCALE",
)
#: Coefficient keys, 20 values each.
COEFF_KEYS = ("LINE_NUM_COEFF", "LINE_DEN_COEFF", "SAMP_NUM_COEFF", "SAMP_DEN_COEFF")

# .RPB (GDAL/DigitalGlobe "IMAGE" group) key names
_RPB_KEYS = {
    "lineOffset": "LINE_OFF",
    "sampOffset": "SAMP_OFF",
    "latOffset": "LAT_OFF",
    "longOffset": "LONG_OFF",
    "heightOffset": "HEIGHT_OFF",
    "lineScale": "LINE_SCALE",
    "sampScale": "SAMP_SCALE",
    "latScale": "LAT_SCALE",
    "longScale": "LONG_SCALE",
    "heightScale": "HEIGHT_SCALE",
    "lineNumCoef": "LINE_NUM_COEFF",
    "lineDenCoef": "LINE_DEN_COEFF",
    "sampNumCoef": "SAMP_NUM_COEFF",
    "sampDenCoef": "SAMP_DEN_COEFF",
    "errBias": "ERR_BIAS",
    "errRand": "ERR_RAND",
}

_BLOCK = 16384  # points per evaluation block (cache-sized monomial matrix: 20 x 16384 doubles)


def _derivative_matrix(axis: int) -> np.ndarray:
    """(20, 10) matrix D with d(term_k)/d(var_axis) = sum_j D[k, j] term_j (j < 10: degree <= 2)."""
    lookup = {tuple(e): j for j, e in enumerate(EXPONENTS[:10])}
    d = np.zeros((20, 10))
    for k, e in enumerate(EXPONENTS):
        if e[axis]:
            e2 = e.copy()
            e2[axis] -= 1
            d[k, lookup[tuple(e2)]] = e[axis]
    return d


_D_L, _D_P = _derivative_matrix(0), _derivative_matrix(1)


def monomials(x, y, z, out=None):
    """The 20 RPC00B terms of normalised ``(x, y, z)`` = (L, P, H) slots, shape (20, n).

    ``x``, ``y``, ``z`` are 1-D float64 arrays of equal length; ``out`` an optional (>= 20, n)
    buffer. 16 multiplications in total, terms reused for numerator and denominator.
    """
    n = x.shape[0]
    m = np.empty((20, n)) if out is None else out
    m[0] = 1.0
    m[1] = x
    m[2] = y
    m[3] = z
    np.multiply(x, y, out=m[4])
    np.multiply(x, z, out=m[5])
    np.multiply(y, z, out=m[6])
    np.multiply(x, x, out=m[7])
    np.multiply(y, y, out=m[8])
    np.multiply(z, z, out=m[9])
    np.multiply(m[4], z, out=m[10])
    np.multiply(m[7], x, out=m[11])
    np.multiply(x, m[8], out=m[12])
    np.multiply(x, m[9], out=m[13])
    np.multiply(m[7], y, out=m[14])
    np.multiply(m[8], y, out=m[15])
    np.multiply(y, m[9], out=m[16])
    np.multiply(m[7], z, out=m[17])
    np.multiply(m[8], z, out=m[18])
    np.multiply(m[9], z, out=m[19])
    return m


#: units that may follow an RPC value (DigitalGlobe/IKONOS text files, and GDAL passes them
#: up raw through the RPC metadata domain): "LINE_OFF: 149.5 pixels"
_UNIT = re.compile(
    r"^\s*([-+0-9.eEdD]+)\s*(?:pixels?|pix|px|degrees?|deg|meters?|metres?|m)?\s*;?\s*$",
    re.IGNORECASE,
)


def _parse_float(value, key, path):
    text = str(value).strip().rstrip(";").strip()
    try:
        v = float(text)
    except (TypeError, ValueError):
        m = _UNIT.match(text)
        try:
            v = float(m.group(1).replace("d", "e").replace("D", "E")) if m else None
        except ValueError:
            v = None
        if v is None:
            raise RPCError(
                f"{where(path)}RPC key {key}: not a number ({str(value)[:40]!r})"
            ) from None
    if not math.isfinite(v):
        raise RPCError(f"{where(path)}RPC key {key}: not finite ({value!r})")
    return v


def _parse_coeffs(value, key, path):
    if isinstance(value, str):
        items = value.replace(",", " ").replace("(", " ").replace(")", " ").split()
    else:
        items = list(value)
    if len(items) != 20:
        raise RPCError(f"{where(path)}RPC key {key}: {len(items)} coefficient(s), expected 20")
    return np.array([_parse_float(v, f"{key}[{i + 1}]", path) for i, v in enumerate(items)])


#: plausible ranges of |offset| and |scale| of an RPC00B normalisation (a scale is a half-width
#: of the validity domain): images up to 10 million pixels a side, any place on the Earth,
#: heights within 100 km of the ellipsoid; smaller scales than the lower bounds describe a
#: domain less than a pixel / a centimetre / a millimetre wide
NORMALISATION_BOUNDS = {
    "line_off": (0.0, 1e7),
    "samp_off": (0.0, 1e7),
    "line_scale": (0.5, 1e7),
    "samp_scale": (0.5, 1e7),
    "lat_off": (0.0, 90.0),
    "lon_off": (0.0, 360.0),
    "lat_scale": (1e-7, 90.0),
    "lon_scale": (1e-7, 180.0),
    "height_off": (0.0, 1e5),
    "height_scale": (1e-3, 1e5),
}
_NORMALISATION_UNITS = {
    "line_off": "px",
    "samp_off": "px",
    "line_scale": "px",
    "samp_scale": "px",
    "lat_off": "deg",
    "lon_off": "deg",
    "lat_scale": "deg",
    "lon_scale": "deg",
    "height_off": "m",
    "height_scale": "m",
}
_RPC_KEY_NAMES = {
    "line_off": "LINE_OFF",
    "samp_off": "SAMP_OFF",
    "line_scale": "LINE_SCALE",
    "samp_scale": "SAMP_SCALE",
    "lat_off": "LAT_OFF",
    "lon_off": "LONG_OFF",
    "lat_scale": "LAT_SCALE",
    "lon_scale": "LONG_SCALE",
    "height_off": "HEIGHT_OFF",
    "height_scale": "HEIGHT_SCALE",
}


class RPCModel(SensorModel):
    """RPC00B sensor model (ground -> image rational polynomials) with exact localisation.

    Parameters
    ----------
    line_num, line_den, samp_num, samp_den : array_like (20,)
        RPC00B coefficients in :data:`RPC00B_TERMS` order.
    line_off, samp_off, line_scale, samp_scale : float
        Image normalisation, pixels (pixel centres at integers, first pixel at 0).
    lon_off, lat_off, lon_scale, lat_scale : float
        Ground normalisation, degrees (WGS84).
    height_off, height_scale : float
        Height normalisation, metres above the WGS84 ellipsoid.
    err_bias, err_rand : float
        RPC00B error estimates, metres (-1 when unknown).
    width, height : int, optional
        Image size (columns, rows); estimated from the image normalisation when absent.
    loc_coeffs : array_like (4, 20), optional
        Vendor image -> ground rational polynomials (DIMAP ``Direct_Model``) as rows
        (lon_num, lon_den, lat_num, lat_den), same normalisation; initial guess of
        :meth:`localize` only.
    source : str, optional
        File the model was read from (for messages).
    """

    def __init__(
        self,
        *,
        line_num,
        line_den,
        samp_num,
        samp_den,
        line_off,
        samp_off,
        line_scale,
        samp_scale,
        lon_off,
        lat_off,
        lon_scale,
        lat_scale,
        height_off,
        height_scale,
        err_bias=-1.0,
        err_rand=-1.0,
        width=None,
        height=None,
        loc_coeffs=None,
        source=None,
    ):
        self.source = str(source) if source else None
        self.line_num = np.asarray(line_num, dtype=np.float64).copy()
        self.line_den = np.asarray(line_den, dtype=np.float64).copy()
        self.samp_num = np.asarray(samp_num, dtype=np.float64).copy()
        self.samp_den = np.asarray(samp_den, dtype=np.float64).copy()
        for name in ("line_num", "line_den", "samp_num", "samp_den"):
            a = getattr(self, name)
            if a.shape != (20,) or not np.all(np.isfinite(a)):
                raise RPCError(f"{where(self.source)}RPC {name}: need 20 finite coefficients")
            # a blank (all-zero) denominator divides by zero everywhere; a numerator without a
            # ground term maps every ground point to one line / column: no image is described
            # (a blank or corrupt RPC; ortho then blamed the DEM for a footprint of NaN)
            blank = not a.any() if name.endswith("_den") else not a[1:].any()
            if blank:
                key = name.replace("samp", "SAMP").replace("line", "LINE").upper() + "_COEFF"
                raise RPCError(
                    f"{where(self.source)}RPC {key}: "
                    + (
                        "all 20 coefficients are zero"
                        if name.endswith("_den") or not a[0]
                        else "no ground-dependent coefficient (only the constant term)"
                    )
                    + "; the RPC is blank or corrupt"
                )
        self.line_off, self.samp_off = float(line_off), float(samp_off)
        self.line_scale, self.samp_scale = float(line_scale), float(samp_scale)
        self.lon_off, self.lat_off = float(lon_off), float(lat_off)
        self.lon_scale, self.lat_scale = float(lon_scale), float(lat_scale)
        self.height_off, self.height_scale = float(height_off), float(height_scale)
        self.err_bias, self.err_rand = float(err_bias), float(err_rand)
        for name in ("line_scale", "samp_scale", "lon_scale", "lat_scale", "height_scale"):
            v = getattr(self, name)
            if not math.isfinite(v) or v == 0.0:
                raise RPCError(
                    f"{where(self.source)}RPC {name.upper()}: must be finite and non-zero ({v})"
                )
        self._check_normalisation()
        self.width = (
            int(width)
            if width
            else max(1, int(math.floor(self.samp_off + abs(self.samp_scale))) + 1)
        )
        self.height = (
            int(height)
            if height
            else max(1, int(math.floor(self.line_off + abs(self.line_scale))) + 1)
        )
        self.loc_coeffs = (
            None if loc_coeffs is None else np.asarray(loc_coeffs, np.float64).reshape(4, 20).copy()
        )
        self._prepare()

    # ------------------------------------------------------------------ internals
    def _check_normalisation(self):
        """:class:`RPCError` naming the key when an offset or scale is physically absurd (a
        corrupt or hand-edited file: e.g. a scale of 1e30 makes every normalised coordinate 0
        and every image size astronomic). Bounds in :data:`NORMALISATION_BOUNDS`."""
        for name, (lo_abs, hi_abs) in NORMALISATION_BOUNDS.items():
            v = abs(getattr(self, name))
            if not lo_abs <= v <= hi_abs:
                unit = _NORMALISATION_UNITS[name]
                raise RPCError(
                    f"{where(self.source)}RPC {_RPC_KEY_NAMES[name]} = {getattr(self, name):g} "
                    f"{unit} is not plausible (|value| must be {lo_abs:g}..{hi_abs:g} {unit}); "
                    "the RPC file is corrupt"
                )

    def _prepare(self):
        # rows: samp_num, samp_den, line_num, line_den
        self._C = np.ascontiguousarray(
            np.stack([self.samp_num, self.samp_den, self.line_num, self.line_den])
        )
        self._CL = np.ascontiguousarray(self._C @ _D_L)  # (4, 10) d/dL in the degree-<=2 terms
        self._CP = np.ascontiguousarray(self._C @ _D_P)
        self._guess = None

    def _affine_guess(self):
        """Affine map normalised (col, row, H, 1) -> (L, P), fitted on projected ground samples."""
        if self._guess is None:
            t = np.linspace(-1.0, 1.0, 9)
            L, P, H = (a.ravel() for a in np.meshgrid(t, t, np.linspace(-1, 1, 5), indexing="ij"))
            m = monomials(L, P, H)
            v = self._C @ m
            with np.errstate(divide="ignore", invalid="ignore"):
                s, l = v[0] / v[1], v[2] / v[3]
            ok = np.isfinite(s) & np.isfinite(l)
            A = np.column_stack([s, l, H, np.ones_like(s)])[ok]
            self._guess, *_ = np.linalg.lstsq(A, np.column_stack([L, P])[ok], rcond=None)
        return self._guess

    # ------------------------------------------------------------------ contract
    def normalised_ground(self, lon, lat, h):
        """Ground points in the RPC's normalised units.

        Returns ``(shape, L, P, H)``: the broadcast shape of ``lon, lat, h`` (degrees, degrees,
        metres above the ellipsoid) and the flattened normalised longitude, latitude and height
        (float64; about [-1, 1] inside the validity range).
        """
        lon, lat, h = broadcast_coordinates(self, lon, lat, h, what="ground coordinates")
        return (
            lon.shape,
            (lon.ravel() - self.lon_off) / self.lon_scale,
            (lat.ravel() - self.lat_off) / self.lat_scale,
            (h.ravel() - self.height_off) / self.height_scale,
        )

    def normalised_image(self, col, row, h):
        """Image points (pixels) at heights ``h`` (m) in the RPC's normalised units.

        Returns ``(shape, c, r, H)``: the broadcast shape and the flattened normalised column
        (sample), row (line) and height (float64).
        """
        col, row, h = broadcast_coordinates(self, col, row, h, what="image coordinates or heights")
        return (
            col.shape,
            (col.ravel() - self.samp_off) / self.samp_scale,
            (row.ravel() - self.line_off) / self.line_scale,
            (h.ravel() - self.height_off) / self.height_scale,
        )

    def project(self, lon, lat, h):
        """Project ground points to the image.

        Parameters
        ----------
        lon, lat : array_like
            Longitude and latitude, degrees (WGS84).
        h : array_like
            Height, metres above the WGS84 ellipsoid. All three broadcast together.

        Returns
        -------
        col, row : ndarray (float64)
            Image coordinates, pixels, centre of the top-left pixel at (0, 0). NaN inputs give
            NaN outputs.

        Notes
        -----
        Points are processed in cache-sized blocks; per block the 20 terms are computed once
        (16 multiplications, :func:`monomials`) and shared by the four polynomials through one
        (4 x 20) @ (20 x n) matrix product, which is faster in numpy than four Horner schemes.
        """
        shape, L, P, H = self.normalised_ground(lon, lat, h)
        n = L.size
        col = np.empty(n)
        row = np.empty(n)
        buf = np.empty((20, min(n, _BLOCK)))
        C = self._C
        for a in range(0, n, _BLOCK):
            b = min(n, a + _BLOCK)
            m = monomials(L[a:b], P[a:b], H[a:b], out=buf[:, : b - a])
            v = C @ m
            np.divide(v[0], v[1], out=col[a:b])
            np.divide(v[2], v[3], out=row[a:b])
        col *= self.samp_scale
        col += self.samp_off
        row *= self.line_scale
        row += self.line_off
        return col.reshape(shape), row.reshape(shape)

    def localize(self, col, row, h, *, tol: float = 1e-6, max_iterations: int = 30):
        """Localise image points at given heights: the exact inverse of :meth:`project`.

        The initial guess comes from the vendor image -> ground polynomials when present
        (:attr:`loc_coeffs`), otherwise from an affine inverse fitted on projected samples of
        the ground domain; then Newton iterations with the analytic 2x2 Jacobian of
        :meth:`project` run until ``|project(localize(x)) - x| <= tol`` pixels in both col and row.

        Parameters
        ----------
        col, row : array_like
            Image coordinates, pixels (centre of the top-left pixel at (0, 0)).
        h : array_like
            Height, metres above the WGS84 ellipsoid. All three broadcast together.
        tol : float
            Convergence threshold, pixels (default 1e-6).
        max_iterations : int
            Newton iteration cap.

        Returns
        -------
        lon, lat : ndarray (float64)
            Degrees (WGS84). Points that did not converge within the cap are NaN and a
            ``RuntimeWarning`` gives their number; NaN inputs give NaN silently.
        """
        shape, cn, rn, H = self.normalised_image(col, row, h)
        n = cn.size
        Lout = np.full(n, np.nan)
        Pout = np.full(n, np.nan)
        # iterate to tol/100 in normalised units so that rounding in the (de)normalisation
        # cannot push the pixel residual over ``tol``
        tol_s, tol_l = 0.01 * tol / abs(self.samp_scale), 0.01 * tol / abs(self.line_scale)
        n_bad = 0
        buf = np.empty((20, min(n, _BLOCK)))
        for a in range(0, n, _BLOCK):
            b = min(n, a + _BLOCK)
            n_bad += self._newton_block(
                cn[a:b], rn[a:b], H[a:b], Lout[a:b], Pout[a:b], tol_s, tol_l, max_iterations, buf
            )
        if n_bad:
            warnings.warn(
                f"{where(self.source)}RPC localisation did not converge to {tol:g} px "
                f"for {n_bad} of {n} point(s); returned NaN",
                RuntimeWarning,
                stacklevel=2,
            )
        lon = Lout * self.lon_scale + self.lon_off
        lat = Pout * self.lat_scale + self.lat_off
        return lon.reshape(shape), lat.reshape(shape)

    def _initial_guess(self, cn, rn, H, buf):
        if self.loc_coeffs is not None:
            m = monomials(cn, rn, H, out=buf[:, : cn.size])
            v = self.loc_coeffs @ m
            return v[0] / v[1], v[2] / v[3]
        g = self._affine_guess()
        return (
            cn * g[0, 0] + rn * g[1, 0] + H * g[2, 0] + g[3, 0],
            cn * g[0, 1] + rn * g[1, 1] + H * g[2, 1] + g[3, 1],
        )

    def _newton_block(self, cn, rn, H, Lout, Pout, tol_s, tol_l, max_iterations, buf):
        """Newton iterations on one block; writes converged (L, P) into Lout/Pout, returns
        #failed."""
        finite = np.isfinite(cn) & np.isfinite(rn) & np.isfinite(H)
        idx = np.flatnonzero(finite)
        if idx.size == cn.size:
            idx = None
            c, r, z = cn, rn, H
        else:
            c, r, z = cn[idx], rn[idx], H[idx]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            L, P = self._initial_guess(c, r, z, buf)
            pos = np.arange(c.size)  # positions (in the block's finite subset) still iterating
            for it in range(max_iterations + 1):
                m = monomials(L, P, z, out=buf[:, : L.size])
                v = self._C @ m
                s = v[0] / v[1]
                ln = v[2] / v[3]
                fs = s - c
                fl = ln - r
                done = (np.abs(fs) <= tol_s) & (np.abs(fl) <= tol_l)
                if done.any():
                    out = pos[done] if idx is None else idx[pos[done]]
                    Lout[out] = L[done]
                    Pout[out] = P[done]
                if done.all() or it == max_iterations:
                    return int((~done).sum())
                g_L = self._CL @ m[:10]
                g_P = self._CP @ m[:10]
                # quotient rule: d(N/D) = (N' - (N/D) D') / D
                sL = (g_L[0] - s * g_L[1]) / v[1]
                sP = (g_P[0] - s * g_P[1]) / v[1]
                lL = (g_L[2] - ln * g_L[3]) / v[3]
                lP = (g_P[2] - ln * g_P[3]) / v[3]
                det = sL * lP - sP * lL
                dL = (fs * lP - fl * sP) / det
                dP = (fl * sL - fs * lL) / det
                keep = ~done
                L = L[keep] - dL[keep]
                P = P[keep] - dP[keep]
                c, r, z, pos = c[keep], r[keep], z[keep], pos[keep]
        return 0  # pragma: no cover

    def height_bounds(self):
        """Validity range of heights (m above the ellipsoid): HEIGHT_OFF -/+ HEIGHT_SCALE."""
        s = abs(self.height_scale)
        return (self.height_off - s, self.height_off + s)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_dict(cls, d, *, path=None, width=None, height=None, loc_coeffs=None):
        """Build from a GDAL RPC-domain mapping (keys of :data:`SCALAR_KEYS` and
        :data:`COEFF_KEYS`).

        Values may be numbers, numeric strings, or (for coefficients) sequences or
        whitespace-separated strings of 20 numbers. ``ERR_BIAS``/``ERR_RAND`` are optional.
        Raises :class:`RPCError` naming ``path`` and the key when one is missing or garbled.
        """
        d = {str(k).upper(): v for k, v in dict(d).items()}
        for k in SCALAR_KEYS + COEFF_KEYS:
            if k not in d or d[k] is None or (isinstance(d[k], str) and not d[k].strip()):
                raise RPCError(f"{where(path)}RPC key {k} missing")
        s = {k: _parse_float(d[k], k, path) for k in SCALAR_KEYS}
        c = {k: _parse_coeffs(d[k], k, path) for k in COEFF_KEYS}
        err = {
            k: _parse_float(d[k], k, path) if k in d and str(d[k]).strip() else -1.0
            for k in ("ERR_BIAS", "ERR_RAND")
        }
        return cls(
            line_num=c["LINE_NUM_COEFF"],
            line_den=c["LINE_DEN_COEFF"],
            samp_num=c["SAMP_NUM_COEFF"],
            samp_den=c["SAMP_DEN_COEFF"],
            line_off=s["LINE_OFF"],
            samp_off=s["SAMP_OFF"],
            line_scale=s["LINE_SCALE"],
            samp_scale=s["SAMP_SCALE"],
            lon_off=s["LONG_OFF"],
            lat_off=s["LAT_OFF"],
            lon_scale=s["LONG_SCALE"],
            lat_scale=s["LAT_SCALE"],
            height_off=s["HEIGHT_OFF"],
            height_scale=s["HEIGHT_SCALE"],
            err_bias=err["ERR_BIAS"],
            err_rand=err["ERR_RAND"],
            width=width,
            height=height,
            loc_coeffs=loc_coeffs,
            source=path,
        )

    @classmethod
    def from_rasterio(cls, rpc, *, width=None, height=None, source=None):
        """Build from a :class:`rasterio.rpc.RPC`."""
        return cls.from_dict(rpc.to_gdal(), path=source, width=width, height=height)

    @classmethod
    def from_file(cls, path, *, direct: bool = False):
        """Read an RPC model, detecting the format.

        Every format of :mod:`stereodem.sensor.io.rpc_formats` (GDAL first, then content
        sniffing); ``direct=True`` localises with the file's direct model
        (:class:`stereodem.sensor.models.rpc_direct.DirectRPCModel`).
        """
        from stereodem.sensor.io.rpc_formats import read_rpc

        return read_rpc(path, direct=direct)

    # ------------------------------------------------------------------ writers
    def to_dict(self) -> dict:
        """GDAL RPC metadata domain (RFC 22) as a dict of strings, exact (17 significant digits)."""
        f = lambda v: format(float(v), ".17g")  # noqa: E731
        d = {
            "LINE_OFF": f(self.line_off),
            "SAMP_OFF": f(self.samp_off),
            "LAT_OFF": f(self.lat_off),
            "LONG_OFF": f(self.lon_off),
            "HEIGHT_OFF": f(self.height_off),
            "LINE_SCALE": f(self.line_scale),
            "SAMP_SCALE": f(self.samp_scale),
            "LAT_SCALE": f(self.lat_scale),
            "LONG_SCALE": f(self.lon_scale),
            "HEIGHT_SCALE": f(self.height_scale),
            "ERR_BIAS": f(self.err_bias),
            "ERR_RAND": f(self.err_rand),
        }
        for key, arr in zip(
            COEFF_KEYS, (self.line_num, self.line_den, self.samp_num, self.samp_den)
        ):
            d[key] = " ".join(f(v) for v in arr)
        return d

    def to_rasterio(self):
        """The model as a :class:`rasterio.rpc.RPC` (for ``RPCTransformer`` or ``rpcs=``)."""
        return RPC(
            height_off=self.height_off,
            height_scale=self.height_scale,
            lat_off=self.lat_off,
            lat_scale=self.lat_scale,
            line_den_coeff=self.line_den.tolist(),
            line_num_coeff=self.line_num.tolist(),
            line_off=self.line_off,
            line_scale=self.line_scale,
            long_off=self.lon_off,
            long_scale=self.lon_scale,
            samp_den_coeff=self.samp_den.tolist(),
            samp_num_coeff=self.samp_num.tolist(),
            samp_off=self.samp_off,
            samp_scale=self.samp_scale,
            err_bias=self.err_bias,
            err_rand=self.err_rand,
        )

    def write_rpb(self, path, *, overwrite=False):
        """Write a GDAL/DigitalGlobe ``.RPB`` file
        (:func:`stereodem.sensor.io.rpc_formats.write_rpb`)."""
        from stereodem.sensor.io.rpc_formats import write_rpb

        return write_rpb(self, path, overwrite=overwrite)

    def write_geotiff_tags(self, path, *, data=None, overwrite=False):
        """Store the RPCs in a GeoTIFF
        (:func:`stereodem.sensor.io.rpc_formats.write_geotiff_rpc`)."""
        from stereodem.sensor.io.rpc_formats import write_geotiff_rpc

        return write_geotiff_rpc(self, path, data=data, overwrite=overwrite)

    def __repr__(self):
        return (
            f"RPCModel({self.width}x{self.height}, lon {self.lon_off:.6f}±{self.lon_scale:.6f}, "
            f"lat {self.lat_off:.6f}±{self.lat_scale:.6f}, h "
            f"{self.height_off:g}±{self.height_scale:g})"
        )
