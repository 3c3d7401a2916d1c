"""Attitude jitter of a pushbroom band: injection, estimation from along-track DEM
residuals, and correction as a time-varying attitude of the sensor model.

ASTER's along-track attitude oscillation (about 1.5 Hz, a few urad) is not in the L1A
geometry (ASTER notes §7 item 12): the backward band 3B then sees the ground a little ahead of
or behind where its model says, and the stereo heights carry stripes across the track that
repeat along it (MMASTER fits them with a sum of sines against a reference DEM; ASP's
``jitter_solve`` adjusts the attitude). Here:

* :func:`with_attitude_sines` gives a copy of a
  :class:`~stereodem.sensor.models.pushbroom.PushbroomModel` (or
  :class:`~stereodem.sensor.models.aster.AsterModel`) whose attitude angle ``axis``
  (``roll``/``pitch``/``yaw``, radians) is ``sum_k a_k sin(2 pi f_k t + phi_k)`` on the model's time
  base - used by the simulator to inject jitter and by the correction;
* :func:`height_sensitivity` is the height change (m per rad) of a stereo intersection when
  the second model's pitch changes, from the two models (numerical, per point);
* :func:`fit_sum_of_sines` finds the strongest frequencies of a sampled signal by a
  Lomb-Scargle periodogram and refines amplitudes, phases and frequencies with
  ``scipy.optimize.least_squares`` (plus a low-order trend);
* :func:`estimate_pitch_jitter` turns DEM-minus-reference residuals into a per-time pitch error
  of the second model (residual / sensitivity, binned by its acquisition line) and fits it;
* :func:`cross_track_sensitivity` and :func:`estimate_roll_jitter` do the same for the roll
  (cross-track) oscillation from the residual vertical parallax of the matches, the offset of
  each right-image match across its epipolar curve (no reference DEM: a roll of the second
  camera moves its image across the epipolar direction, which two images observe, while a
  pitch moves it along, where it reads as height).

3N and 3B see the same ground about 55 s apart, so one platform oscillation reaches the two
bands with unrelated phases; only the difference is observable from the pair, and it is
attributed to the second (3B) model, as MMASTER does.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from stereodem.core import geodesy
from stereodem.core.dem import ELLIPSOID
from stereodem.core.errors import InputError
from stereodem.sensor.models.ephemeris import Attitude

_AXES = {"roll": 0, "pitch": 1, "yaw": 2}


@dataclass
class SineSeries:
    """``y(t) = sum_k amplitude_k sin(2 pi frequency_k t + phase_k)`` (t in seconds).

    ``amplitudes`` in the signal's unit (radians for attitude), ``frequencies`` in Hz.
    ``trend`` holds polynomial coefficients (ascending, in ``(t - t_ref)``) fitted alongside
    and not part of the correction; ``rms_residual`` is the RMS misfit of the samples within
    five robust sigmas.
    """

    amplitudes: np.ndarray
    frequencies: np.ndarray
    phases: np.ndarray
    t_ref: float = 0.0
    trend: np.ndarray = field(default_factory=lambda: np.zeros(1))
    rms_residual: float = float("nan")

    def __call__(self, t):
        t = np.asarray(t, float)[..., None]
        return np.sum(self.amplitudes * np.sin(2 * np.pi * self.frequencies * t + self.phases), -1)

    def to_dict(self) -> dict:
        return {
            "amplitudes": self.amplitudes.tolist(),
            "frequencies_hz": self.frequencies.tolist(),
            "phases_rad": self.phases.tolist(),
            "t_ref": self.t_ref,
            "trend": self.trend.tolist(),
            "rms_residual": self.rms_residual,
        }


#: the largest attitude oscillation a model takes, radians (ASTER's jitter is a few
#: microradians; 10 mrad moves the image by about 470 ASTER pixels: a new pointing, not an
#: oscillation)
MAX_OSCILLATION_RAD = 0.01


#: the slowest sine a fit takes: one thousandth of a cycle over the samples' time span (a
#: slower one is the polynomial trend fitted beside the sines; a band of 1e-300 Hz fitted
#: radians of roll, and SciPy 1.10's Lomb-Scargle aborted the process on 5e-324 Hz)
MIN_CYCLES_PER_SPAN = 1e-3


def check_slowest_frequency(f_min, span_s: float, what="the lowest frequency") -> None:
    """:class:`InputError` unless ``f_min`` (Hz) is finite and at least
    :data:`MIN_CYCLES_PER_SPAN` cycles over ``span_s`` seconds."""
    floor = MIN_CYCLES_PER_SPAN / max(float(span_s), 1e-300)
    if not (np.isfinite(f_min) and f_min >= floor):
        raise InputError(
            f"{what} of {f_min:g} Hz is slower than {floor:.3g} Hz, {MIN_CYCLES_PER_SPAN:g} "
            f"cycle over the {span_s:.3g} s the samples span: the trend fitted beside the "
            "sines, not an oscillation"
        )


def check_line_nyquist(model, frequencies, what="an attitude oscillation") -> None:
    """:class:`InputError` unless every frequency (Hz) of ``frequencies`` is finite and at most
    half the line rate of the pushbroom ``model``: its image lines sample the attitude once
    each, so a faster oscillation aliases (and a spline of it had no bound: 1e308 Hz was an
    OverflowError, and a fit over such a band a LinAlgError)."""
    f = np.atleast_1d(np.asarray(frequencies, dtype=float))
    if not f.size:
        return
    nyquist = 0.5 / abs(float(model.line_time(1)) - float(model.line_time(0)))
    f_max = float(np.max(f))
    if not (np.all(np.isfinite(f)) and f_max <= nyquist):
        raise InputError(
            f"{model.name}: {what} of {f_max:g} Hz is faster than half the line rate "
            f"({nyquist:.4g} Hz); the image lines cannot sample it"
        )


def with_attitude_sines(
    model,
    series: SineSeries,
    *,
    axis: str = "pitch",
    sign: float = 1.0,
    samples_per_period: int = 40,
):
    """Copy of a pushbroom ``model`` whose attitude angle ``axis`` follows ``sign * series(t)``.

    The oscillation is sampled (``samples_per_period`` per shortest period, natural cubic
    spline of :class:`~stereodem.sensor.models.ephemeris.Attitude`) over the image's time span
    plus a margin, and composed with any attitude the model already has.
    """
    if axis not in _AXES:
        raise InputError(f"attitude axis must be one of {', '.join(_AXES)}, got {axis!r}")
    f_max = float(np.max(series.frequencies)) if len(series.frequencies) else 1.0
    t0 = float(model.line_time(-0.05 * model.height - 50))
    t1 = float(model.line_time(1.05 * model.height + 50))
    check_line_nyquist(model, series.frequencies)
    amplitudes = np.abs(np.asarray(series.amplitudes, float))
    if amplitudes.size and not np.all(amplitudes <= MAX_OSCILLATION_RAD):
        # e.g. a fit over a band of 1e-300 Hz, whose sines are flat over the image: their
        # amplitudes grew without bound and the corrected model pointed anywhere
        raise InputError(
            f"{model.name}: an attitude oscillation of {float(np.max(amplitudes)):.3g} rad "
            f"({axis}) is beyond {MAX_OSCILLATION_RAD:g} rad: a new pointing, not an oscillation"
        )
    n = max(16, int(np.ceil((t1 - t0) * f_max * samples_per_period)) + 1)
    t = np.linspace(t0, t1, n)
    angles = np.zeros((n, 3))
    angles[:, _AXES[axis]] = sign * series(t)
    if model.attitude is not None:
        if model.attitude.angles is None:
            raise InputError(f"{model.name}: cannot add sines to a quaternion attitude")
        angles += model.attitude.angles_at(t)
    new = copy.copy(model)
    new.attitude = Attitude(t, angles)
    return new


def height_sensitivity(left, right, lon, lat, h, *, dpitch: float = 1e-6):
    """d(height)/d(pitch of ``right``) in m/rad at ground points, by space intersection.

    The point is seen by ``left`` and ``right``; ``right`` is pitched by ``dpitch`` and the two
    rays are intersected again (closest point of the two lines).
    """
    cl, rl = left.project(lon, lat, h)
    cr, rr = right.project(lon, lat, h)
    tilted = right.with_parameters(pitch_bias=right.parameters()["pitch_bias"] + dpitch)
    o1, d1 = left.rays(cl, rl)
    o2, d2 = tilted.rays(cr, rr)
    w = o1 - o2
    a, b, c = (d1 * d1).sum(-1), (d1 * d2).sum(-1), (d2 * d2).sum(-1)
    d, e = (d1 * w).sum(-1), (d2 * w).sum(-1)
    den = a * c - b * b
    s = (b * e - c * d) / den
    u = (a * e - b * d) / den
    p = 0.5 * ((o1 + s[..., None] * d1) + (o2 + u[..., None] * d2))
    _, _, hp = geodesy.ecef_to_geodetic(p[..., 0], p[..., 1], p[..., 2])
    return (np.asarray(hp) - np.asarray(h, float)) / dpitch


def fit_sum_of_sines(
    t, y, *, n_sines: int = 1, f_range=(0.2, 8.0), trend_degree: int = 1, n_frequencies: int = 2000
) -> SineSeries:
    """Fit ``n_sines`` sines (and a polynomial trend) to samples ``(t, y)``.

    Frequencies are located one after another on the Lomb-Scargle periodogram of the residual
    (``scipy.signal.lombscargle``) within ``f_range`` (Hz), then all parameters are refined
    together by ``scipy.optimize.least_squares`` (soft-L1 loss against outliers).
    """
    # imported here: scipy.signal loads scipy.stats (0.2 s together), which every command
    # importing the jitter correction would pay, and only this fit needs it
    from scipy.signal import lombscargle

    t = np.asarray(t, float)
    y = np.asarray(y, float)
    ok = np.isfinite(t) & np.isfinite(y)
    t, y = t[ok], y[ok]
    if t.size < 4 * n_sines + trend_degree + 2:
        raise InputError(f"jitter fit: only {t.size} valid samples")
    check_slowest_frequency(
        f_range[0], float(t.max() - t.min()), "jitter fit: the lowest frequency"
    )
    t_ref = float(np.mean(t))
    x = t - t_ref
    # initial search on the samples that are not outliers (median +- 5 robust sigmas)
    dev = y - np.median(y)
    inl = np.abs(dev) <= 5.0 * 1.4826 * max(float(np.median(np.abs(dev))), 1e-300)
    xs = x[inl]
    trend = np.polynomial.polynomial.polyfit(xs, y[inl], trend_degree)
    resid = y[inl] - np.polynomial.polynomial.polyval(xs, trend)
    freqs = np.linspace(f_range[0], f_range[1], n_frequencies)
    amps, fs, phs = [], [], []
    for _ in range(n_sines):
        power = lombscargle(xs, resid - resid.mean(), 2 * np.pi * freqs)
        f = float(freqs[np.argmax(power)])
        a = np.stack([np.sin(2 * np.pi * f * xs), np.cos(2 * np.pi * f * xs)], -1)
        (sa, ca), *_ = np.linalg.lstsq(a, resid, rcond=None)
        amps.append(np.hypot(sa, ca))
        phs.append(np.arctan2(ca, sa))
        fs.append(f)
        resid = resid - a @ np.array([sa, ca])
    p0 = np.concatenate([amps, fs, phs, trend])
    k, nd = n_sines, trend_degree + 1

    def model(p):
        a, f, ph, c = p[:k], p[k : 2 * k], p[2 * k : 3 * k], p[3 * k :]
        return np.sum(
            a * np.sin(2 * np.pi * f * x[:, None] + ph), -1
        ) + np.polynomial.polynomial.polyval(x, c)

    scale = float(np.median(np.abs(y - model(p0)))) * 1.4826 or 1e-12
    sol = least_squares(lambda p: model(p) - y, p0, loss="soft_l1", f_scale=scale)
    p = sol.x
    a, f, ph = p[:k], p[k : 2 * k], p[2 * k : 3 * k]
    ph = ph - 2 * np.pi * f * t_ref  # phases on the absolute time base
    sgn = np.sign(a)
    ph = np.where(sgn < 0, ph + np.pi, ph)
    r = model(p) - y
    rms = float(np.sqrt(np.mean(r[np.abs(r) <= 5.0 * 1.4826 * np.median(np.abs(r))] ** 2)))
    return SineSeries(np.abs(a), f, np.mod(ph, 2 * np.pi), t_ref, p[3 * k : 3 * k + nd], rms)


def along_track_profile(values, model, lon, lat, h, *, bin_lines: float = 8.0):
    """Median of ``values`` per bin of ``model`` acquisition lines: ``(times, medians, counts)``."""
    ok = np.isfinite(values) & np.isfinite(h)
    _, row = model.project(lon[ok], lat[ok], h[ok])
    v = values[ok]
    good = np.isfinite(row)
    row, v = row[good], v[good]
    if row.size == 0:
        raise InputError("jitter: no DEM cell projects into the image")
    edges = np.arange(np.floor(row.min()), np.ceil(row.max()) + bin_lines, bin_lines)
    idx = np.digitize(row, edges) - 1
    order = np.argsort(idx, kind="stable")
    idx_s, v_s = idx[order], v[order]
    starts = np.flatnonzero(np.r_[True, np.diff(idx_s) > 0])
    groups = np.split(v_s, starts[1:])
    centres = 0.5 * (edges[idx_s[starts]] + edges[idx_s[starts] + 1])
    med = np.array([np.median(g) for g in groups])  # one call per bin, not per cell
    counts = np.array([g.size for g in groups])
    return model.line_time(centres), med, counts


def estimate_pitch_jitter(
    dem,
    reference,
    left,
    right,
    *,
    n_sines: int = 1,
    f_range=(0.2, 8.0),
    bin_lines: float = 8.0,
    min_count: int = 20,
    max_cells: int = 200_000,
    seed: int = 0,
):
    """Pitch jitter of ``right`` (rad, on its time base) from ``dem - reference`` residuals.

    ``dem`` and ``reference`` are :class:`~stereodem.core.dem.DEM` objects with
    ellipsoidal heights (``reference`` is sampled at ``dem``'s cells). A camera whose true
    pitch is ``j(t)`` above its model's gives heights off by ``-j(t) * sensitivity``; so each
    residual is divided by minus the local :func:`height_sensitivity` (m/rad) and binned by
    the ``right`` acquisition line; bins with fewer than ``min_count`` cells are dropped. The
    fitted :class:`SineSeries` is ``j(t)``: ``with_attitude_sines(right, fit)`` is the
    corrected model. Returns ``(SineSeries, diagnostics)`` with the profile used.
    """
    z = np.asarray(dem.heights, float)
    rows, cols = np.nonzero(np.isfinite(z))
    if rows.size > max_cells:
        pick = np.random.default_rng(seed).choice(rows.size, max_cells, replace=False)
        rows, cols = rows[pick], cols[pick]
    x, y = dem.transform @ (cols + 0.5, rows + 0.5)
    lon, lat = geodesy.crs_to_lonlat(np.asarray(x), np.asarray(y), dem.crs)
    h = z[rows, cols]
    ref = (
        reference.sample(lon, lat, reference=ELLIPSOID)
        if hasattr(reference, "sample")
        else reference
    )
    dh = h - np.asarray(ref, float)
    sens = height_sensitivity(left, right, lon, lat, h)
    t, med, counts = along_track_profile(-dh / sens, right, lon, lat, h, bin_lines=bin_lines)
    keep = counts >= min_count
    fit = fit_sum_of_sines(t[keep], med[keep], n_sines=n_sines, f_range=f_range)
    return fit, {
        "times": t[keep],
        "pitch_profile_rad": med[keep],
        "counts": counts[keep],
        "sensitivity_m_per_rad": float(np.median(sens)),
    }


def cross_track_sensitivity(right, lon, lat, h, normal, *, droll: float = 1e-6):
    """Displacement (px per rad) of ``right``'s projection of ground points across the
    epipolar curves (unit ``normal`` vectors (N, 2) in right-image (col, row)) when the
    camera rolls by ``droll``: the factor turning a vertical-parallax residual into a roll."""
    c0, r0 = right.project(lon, lat, h)
    rolled = right.with_parameters(roll_bias=right.parameters()["roll_bias"] + droll)
    c1, r1 = rolled.project(lon, lat, h)
    n = np.asarray(normal, float)
    return ((np.asarray(c1) - c0) * n[..., 0] + (np.asarray(r1) - r0) * n[..., 1]) / droll


def roll_profile(times, cross_px, sensitivity, *, bin_seconds: float, min_count: int = 20):
    """Per-time roll (rad) of the second camera from vertical-parallax residuals.

    ``cross_px`` are the signed residuals across the epipolar curves (px) of matches whose
    right-image acquisition times are ``times`` (s); ``sensitivity`` (px/rad, per match or
    scalar) from :func:`cross_track_sensitivity`. Each residual divided by its sensitivity is
    a roll sample; samples are binned by time (``bin_seconds``) and the median of each bin
    with at least ``min_count`` samples kept. Returns ``(bin_times, roll_rad, counts)``.
    """
    t = np.asarray(times, float)
    roll = np.asarray(cross_px, float) / np.asarray(sensitivity, float)
    ok = np.isfinite(t) & np.isfinite(roll)
    t, roll = t[ok], roll[ok]
    if t.size == 0:
        raise InputError("roll jitter: no valid vertical-parallax sample")
    edges = np.arange(t.min(), t.max() + bin_seconds, bin_seconds)
    idx = np.clip(np.digitize(t, edges) - 1, 0, max(len(edges) - 2, 0))
    order = np.argsort(idx, kind="stable")
    idx_s, v_s, t_s = idx[order], roll[order], t[order]
    starts = np.flatnonzero(np.r_[True, np.diff(idx_s) > 0])
    groups = np.split(v_s, starts[1:])
    tgroups = np.split(t_s, starts[1:])
    med = np.array([np.median(g) for g in groups])  # one call per bin, not per sample
    tm = np.array([np.mean(g) for g in tgroups])
    counts = np.array([g.size for g in groups])
    keep = counts >= min_count
    return tm[keep], med[keep], counts[keep]


def estimate_roll_jitter(
    times,
    cross_px,
    sensitivity,
    *,
    n_sines: int = 1,
    f_range=(0.2, 8.0),
    bin_seconds: float = 8 * 2.1989e-3,
    min_count: int = 20,
):
    """Roll jitter of the second camera (rad, on its time base) from the matcher's residual
    vertical parallax (see :func:`roll_profile`): a :class:`SineSeries` fitted by
    :func:`fit_sum_of_sines` (periodogram, then least squares), and the profile used.

    A camera whose true roll is ``j(t)`` above its model's shows its matches ``j(t) *
    sensitivity`` px across the model's epipolar curves, so the fitted series is ``j(t)``:
    ``with_attitude_sines(right, fit, axis="roll")`` is the corrected model.
    """
    t, roll, counts = roll_profile(
        times, cross_px, sensitivity, bin_seconds=bin_seconds, min_count=min_count
    )
    fit = fit_sum_of_sines(t, roll, n_sines=n_sines, f_range=f_range)
    return fit, {"times": t, "roll_profile_rad": roll, "counts": counts}


def fit_at_frequencies(t, y, frequencies, *, trend_degree: int = 1, t_ref: float = 0.0):
    """Amplitudes and phases of sines at fixed ``frequencies`` (Hz) in samples ``(t, y)``:
    linear least squares with a polynomial trend, refitted once without the samples beyond
    five robust sigmas. Returns a :class:`SineSeries` on the absolute time base."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    ok = np.isfinite(t) & np.isfinite(y)
    t, y = t[ok], y[ok]
    f = np.asarray(frequencies, float)
    if t.size < 2 * f.size + trend_degree + 2:
        raise InputError(f"jitter fit: only {t.size} valid samples")
    x = t - float(np.mean(t))
    w = 2 * np.pi * f
    a = np.concatenate(
        [
            np.sin(np.outer(t, w)),
            np.cos(np.outer(t, w)),
            np.vander(x, trend_degree + 1, increasing=True),
        ],
        1,
    )
    keep = np.ones(t.size, bool)
    for _ in range(2):
        c, *_ = np.linalg.lstsq(a[keep], y[keep], rcond=None)
        r = y - a @ c
        keep = np.abs(r) <= 5.0 * 1.4826 * max(float(np.median(np.abs(r[keep]))), 1e-300)
    s, co = c[: f.size], c[f.size : 2 * f.size]  # a sin(wt + p) = a cos p sin wt + a sin p cos wt
    return SineSeries(
        np.hypot(s, co),
        f,
        np.mod(np.arctan2(co, s), 2 * np.pi),
        t_ref,
        c[2 * f.size :],
        float(np.sqrt(np.mean(r[keep] ** 2))),
    )


def add_series(a: SineSeries, b: SineSeries) -> SineSeries:
    """The sum of two sine series at the same frequencies, as one (phasors added)."""
    if a.frequencies.shape != b.frequencies.shape or not np.allclose(a.frequencies, b.frequencies):
        raise InputError("add_series: the two series must have the same frequencies")
    s = a.amplitudes * np.cos(a.phases) + b.amplitudes * np.cos(b.phases)
    c = a.amplitudes * np.sin(a.phases) + b.amplitudes * np.sin(b.phases)
    return SineSeries(
        np.hypot(s, c),
        a.frequencies.copy(),
        np.mod(np.arctan2(c, s), 2 * np.pi),
        a.t_ref,
        a.trend,
        b.rms_residual,
    )
