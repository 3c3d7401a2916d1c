"""JSON of numpy values: the ``default=`` hook every JSON writer of the project uses."""

from __future__ import annotations

import numpy as np


def json_default(o):
    """numpy scalars -> Python numbers, arrays -> lists, anything else -> ``str``."""
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
