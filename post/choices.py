"""Option choices of the post-processing commands, as the command line takes them (a light
module: no numpy, so that a command's parser loads none)."""

from typing import Literal, get_args

#: value per output cell of a mosaic (:func:`stereodem.post.mosaic.plan_mosaic`)
MosaicMethod = Literal[
    "blend", "first", "last", "min", "max", "mean", "median", "count", "stddev", "nmad"
]
MOSAIC_METHODS: tuple[str, ...] = get_args(MosaicMethod)
