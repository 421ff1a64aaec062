"""The one place that sets how the control kernels are compiled and called.

numba compiles the per-sample kernels (estimator, law, inversion) to machine code; the
compiled code is cached on disk beside the sources, so only the first process after an install
pays the compile time. ``NUMBA_DISABLE_JIT=1`` runs the same functions as plain Python.

A call from Python into a kernel costs numba's dispatcher a type resolution of every argument.
The servo cycle's calls therefore pass their arrays as one :func:`bundle` (a numba StructRef:
the arrays by name, shared with Python, not copied) and go through :func:`entry`, the compiled
overload itself (the cost of the call: ``benchmarks/bench_loop.py``, "the compiled call of a
cycle").
"""

from functools import partial
from types import SimpleNamespace

from numba import config as _config
from numba import njit as _numba_njit
from numba import typeof as _typeof
from numba.core import types as _types
from numba.experimental import structref as _structref

#: Decorator for the per-sample kernels: nopython mode, cached, no GIL needed.
njit = partial(_numba_njit, cache=True, nogil=True)

#: True when ``NUMBA_DISABLE_JIT=1``: kernels are plain Python
DISABLED = bool(_config.DISABLE_JIT)

__all__ = ["DISABLED", "BundleType", "bundle", "define_bundle", "entry", "njit"]


class BundleType(_types.StructRef):
    """Base of the bundles' numba types: the field types as given (no literal types)."""

    def preprocess_fields(self, fields):
        return tuple((name, _types.unliteral(t)) for name, t in fields)


def define_bundle(type_cls, proxy_cls, fields) -> None:
    """Make ``proxy_cls`` (a subclass of numba's ``StructRefProxy``) a bundle of named arrays
    with the numba type ``type_cls`` (a subclass of this module's bundle type): its constructor
    takes the fields in order, and kernels read them as attributes (``st.pos``). Both classes
    must be defined at module level, so that kernels taking a bundle are cached on disk.

    Args:
        type_cls: the numba type class (not registered yet).
        proxy_cls: the Python-side class.
        fields: the field names, in constructor order.
    """
    _structref.register(type_cls)
    _structref.define_constructor(proxy_cls, type_cls, list(fields))
    _structref.define_boxing(type_cls, proxy_cls)


def bundle(make, fields, arrays):
    """A bundle built by ``make`` (a kernel that calls the bundle's constructor, so that the
    construction is compiled once and cached) from ``arrays``, one per name of ``fields``; with
    the JIT disabled, a namespace with the same attributes.

    The bundle holds the arrays themselves: writes from either side are seen by the other.
    A field that is replaced in Python (a new array) needs a new bundle.
    """
    if DISABLED:
        return SimpleNamespace(**dict(zip(fields, arrays)))
    return make(*arrays)


def entry(kernel, *args):
    """The compiled overload of ``kernel`` for the types of ``args`` (compiled now, or loaded
    from the cache), callable from Python without the dispatcher's type resolution.

    The caller must pass arguments of exactly these types at every call: the overload checks
    no more than an array's item size. With the JIT disabled, ``kernel`` itself.

    Raises:
        numba's TypingError when the kernel does not compile for these types.
    """
    if DISABLED:
        return kernel
    return kernel.compile(tuple(_typeof(a) for a in args))
