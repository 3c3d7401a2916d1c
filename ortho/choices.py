"""Option choices of the orthoimage and uncertainty steps, as the command line, the
configuration checks and the docs take them (a light module: no OpenCV)."""

from typing import Literal, get_args

#: image resampling of the orthoimage (OpenCV kernels, :data:`stereodem.ortho.drm.RESAMPLING`)
Resampling = Literal["nearest", "bilinear", "cubic", "lanczos"]
RESAMPLINGS: tuple[str, ...] = get_args(Resampling)

#: propagation of the model covariance to the uncertainty maps
UncertaintyMethod = Literal["first-order", "monte-carlo", "fast"]
UNCERTAINTY_METHODS: tuple[str, ...] = get_args(UncertaintyMethod)
