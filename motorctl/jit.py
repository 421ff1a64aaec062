"""The one place that sets how the control kernels are compiled.

numba compiles the per-sample kernels (estimator, law, inversion) to machine code; the
compiled code is cached on disk beside the sources, so only the first process after an install
pays the compile time. ``NUMBA_DISABLE_JIT=1`` runs the same functions as plain Python.
"""

from functools import partial

from numba import njit as _numba_njit

#: Decorator for the per-sample kernels: nopython mode, cached, no GIL needed.
njit = partial(_numba_njit, cache=True, nogil=True)
