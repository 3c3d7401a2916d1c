"""Option choices of the orthoimage and uncertainty steps, as the command line, the
configuration checks and the docs take them, and the bounds of the uncertainty inputs that
both check (a light module: no OpenCV, no SciPy)."""

import math
import numbers
from typing import Literal, get_args

from stereodem.core.errors import InputError

#: image resampling of the orthoimage (OpenCV kernels, :data:`stereodem.ortho.drm.RESAMPLING`)
Resampling = Literal["nearest", "bilinear", "cubic", "lanczos"]
RESAMPLINGS: tuple[str, ...] = get_args(Resampling)

#: propagation of the model covariance to the uncertainty maps
UncertaintyMethod = Literal["first-order", "monte-carlo", "fast"]
UNCERTAINTY_METHODS: tuple[str, ...] = get_args(UncertaintyMethod)

#: the samples of the sampling methods: at least 10, at most 10^5 (the Monte Carlo σ's own
#: sampling error, 1/sqrt(2N), is then 0.2 %; on the 300 x 300 test scene 1000 draws took
#: 27 s and 20000 took 285 s on a 2-core machine also running the test suite, and 99999999999
#: ended "out of memory")
MIN_SAMPLES, MAX_SAMPLES = 10, 100_000


def check_samples(samples, what: str = "--samples") -> int:
    """``samples`` within :data:`MIN_SAMPLES` .. :data:`MAX_SAMPLES`, else
    :class:`InputError` naming ``what``; the rule of ``--samples`` and ``[uncertainty]
    samples``."""
    if isinstance(samples, bool) or not isinstance(samples, numbers.Integral):
        raise InputError(f"{what} must be a whole number, got {samples!r}")
    if not MIN_SAMPLES <= samples <= MAX_SAMPLES:
        raise InputError(
            f"{what} must be {MIN_SAMPLES}..{MAX_SAMPLES} (Monte Carlo draws or FAST points "
            f"per curve), got {samples}"
        )
    return int(samples)


def check_input_sigma(value, what: str) -> float:
    """``value`` as the σ of an uncertainty input: a number >= 0 whose variance σ² is finite
    (1e308 passed the finite check and overflowed squaring it: an OverflowError traceback),
    else :class:`InputError` naming ``what``. The rule of ``--sigma`` and ``[uncertainty]
    sigma``."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and value >= 0 and math.isfinite(float(value) * float(value))):
        raise InputError(
            f"{what}: sigma must be a finite non-negative number whose square (the variance) "
            f"is finite, got {value!r}"
        )
    return float(value)
