"""Array helpers the test files share."""

from __future__ import annotations

import numpy as np


def host(array) -> np.ndarray:
    """A backend's array as a host NumPy array: Warp's GPU arrays need `.numpy()`, JAX's and
    NumPy's convert as they are (`np.asarray` of a Warp array on a GPU raises)."""
    if hasattr(array, "numpy") and not isinstance(array, np.ndarray):
        array = array.numpy()
    return np.asarray(array)
