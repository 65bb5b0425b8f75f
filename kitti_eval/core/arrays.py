"""How every kernel takes its arrays.

numba compiles one version of a kernel per combination of argument types, and a read-only or strided
array is another type than a writeable C-contiguous one. The wrappers in :mod:`kitti_eval.core` and
:mod:`kitti_eval.analysis` pass every array through :func:`kernel_input` first, so each kernel is compiled
once and cached once whatever the caller handed over (``tests/core/test_jit.py`` counts the compilations).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["kernel_input"]


def kernel_input(value: npt.ArrayLike, dtype: npt.DTypeLike) -> np.ndarray:
    """``value`` as every kernel takes its arrays: C-contiguous, of ``dtype``, writeable (numba compiles a
    separate version for read-only arrays). Copies only when it must."""
    return np.require(value, dtype, ("C", "W"))
