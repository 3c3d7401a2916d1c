"""Option choices of the post-processing commands, as the command line takes them, and the
file names of their quick-look figures (a light module: no numpy, so that a command's parser
and its product list load none)."""

from typing import Literal, get_args

#: value per output cell of a mosaic (:func:`stereodem.post.mosaic.plan_mosaic`)
MosaicMethod = Literal[
    "blend", "first", "last", "min", "max", "mean", "median", "count", "stddev", "nmad"
]
MOSAIC_METHODS: tuple[str, ...] = get_args(MosaicMethod)


#: the quick-look figures of ``stereodem change`` (:mod:`stereodem.post.product_figures`)
CHANGE_FIGURES = {"dh_map": "dh_map.png", "dh_sigma_map": "dh_sigma_map.png"}
#: the quick-look figures of ``stereodem stack``
STACK_FIGURES = {
    "rate_map": "rate_map.png",
    "rate_sigma_map": "rate_sigma_map.png",
    "n_obs_map": "n_obs_map.png",
}
