"""The one place that sets how the control kernels are compiled and called.

numba compiles the per-sample kernels (estimator, law, inversion) to machine code; the
compiled code is cached on disk in a folder keyed by the package's sources
(:mod:`motorctl.jitcache`, set before numba reads its configuration), so only the first process
after an install or an edit pays the compile time. ``NUMBA_DISABLE_JIT=1`` runs the same
functions as plain Python.

Inside compiled code every array view (a slice, a row, a bundle's field) and every array
passed on to another kernel is reference-counted: an atomic increment and decrement of its
owner's count, which numba cannot prune across the branches and loops of a law. In the servo
cycle those pairs cost more than the arithmetic (the C2 step on the 2-core development VM:
1.30 µs with them, 0.73 µs without, ``benchmarks/bench_loop.py``). The cycle's kernels
therefore take their views through :func:`borrow`, a view without a reference (its counting
calls return at once): safe because each such view lives only inside the call that made it,
while the caller holds its owner.

A call from Python into a kernel costs numba's dispatcher a type resolution of every argument.
The servo cycle's calls therefore pass their arrays as one :func:`bundle` (a numba StructRef:
the arrays by name, shared with Python, not copied) and go through :func:`entry`, the compiled
overload itself (the cost of the call: ``benchmarks/bench_loop.py``, "the compiled call of a
cycle").

numba itself is imported when the first kernel is compiled or loaded (:func:`load`), not when
a module defines one: :func:`njit` wraps the function in a :class:`Kernel` that becomes numba's
dispatcher at its first use. A process that only reads the kernels' modules (``motorctl
identify``, which fits in numpy and scipy, and calls no kernel) does not pay numba's import
(0.25-0.45 s of its start-up, ``benchmarks/bench_ident.py``).
"""

import functools
import operator
import os
from types import SimpleNamespace

import numpy as np


def _disabled_by_environment() -> bool:
    try:
        return bool(int(os.environ.get("NUMBA_DISABLE_JIT", "0") or "0"))
    except ValueError:
        return False


#: True when ``NUMBA_DISABLE_JIT=1``: kernels are plain Python. Read from the environment as
#: numba reads it (an integer; unset: 0), before numba is imported (:func:`load` checks that
#: numba's own configuration agrees)
DISABLED = _disabled_by_environment()

__all__ = ["DISABLED", "BundleType", "Kernel", "borrow", "bundle", "check_code", "copy_into",
           "define_bundle", "dispatch", "dispatcher_of", "entry", "load", "njit"]

#: numba's parts, once :func:`load` imported it
_numba = None


def load() -> SimpleNamespace:
    """numba, imported once per process: its cache folder set first (:mod:`motorctl.jitcache`;
    numba reads ``NUMBA_CACHE_DIR`` at its import, a kernel's cache locator when the kernel is
    created, after this). Returns numba's ``njit``, ``typeof``, ``types``, ``structref`` and
    ``intrinsic``.

    Raises:
        RuntimeError: numba's own configuration (a ``.numba_config.yaml``) disables the JIT where
            ``NUMBA_DISABLE_JIT`` in the environment, which decided how the kernels were
            defined (:data:`DISABLED`), does not, or the reverse.
    """
    global _numba
    if _numba is None:
        from motorctl.jitcache import numba_folder
        folder = numba_folder()              # before numba reads NUMBA_CACHE_DIR
        from numba import config, njit, typeof
        from numba.core import types
        from numba.experimental import structref
        from numba.extending import intrinsic
        if folder is not None:
            # numba read NUMBA_CACHE_DIR at its import (before motorctl's, or without a plugin
            # folder): a kernel's cache locator reads the setting when the kernel is created.
            # numba's compiler re-reads the environment at every compile when a NUMBA_ variable
            # changed since numba last read it (numba.core.config.reload_config), and would put
            # the environment's folder back: when numba was imported before
            # jitcache.configure set NUMBA_CACHE_DIR, a plugin process cached its first kernel
            # in the plugin folder and every later one (the plant's and the cycle's dispatch
            # over its kernel tables) in the plain install's, where plain processes then
            # loaded them. Read the environment now, then set the folder.
            config.reload_config()
            config.CACHE_DIR = folder
        if bool(config.DISABLE_JIT) != DISABLED:
            raise RuntimeError(f"numba's DISABLE_JIT is {config.DISABLE_JIT} but NUMBA_DISABLE_JIT in the "
                               f"environment is {os.environ.get('NUMBA_DISABLE_JIT', 'unset')}: set it in the "
                               "environment, not in a .numba_config.yaml")
        _numba = SimpleNamespace(njit=njit, typeof=typeof, types=types, structref=structref, intrinsic=intrinsic)
    return _numba


class Kernel:
    """A function compiled by numba (nopython mode, cached on disk, no GIL needed) at its first
    use: a call from Python, the typing of a compiled caller that calls it, or any attribute of
    numba's dispatcher (``compile``, ``overloads``, ...), which it then forwards to.

    ``py_func`` is the Python function; ``__name__``, ``__qualname__``, ``__module__`` and
    ``__doc__`` are its. Compiled callers see numba's dispatcher itself (its type, ``types.Dispatcher``),
    so they compile and cache as if the module had defined the dispatcher. Pickles as numba's
    dispatcher (numba's cache pickles a closure's variables into its index key).
    """

    def __init__(self, py_func):
        self.py_func = py_func
        functools.update_wrapper(self, py_func)

    #: a call is numba's dispatcher's own: the property's getter is C code (``attrgetter`` of
    #: the instance's ``dispatcher``), no Python frame (through a method the heartbeat's release
    #: store cost 190 ns a call more than the dispatcher's, this way 70-150 ns; a hot path
    #: calls :func:`dispatcher_of` instead)
    __call__ = property(operator.attrgetter("dispatcher"))

    @property
    def _numba_type_(self):
        # numba's typeof of a global or closure variable: the dispatcher's own type
        return self.dispatcher._numba_type_

    def __getattr__(self, name):
        # called for names the instance does not hold: ``dispatcher`` before the first use
        # (created, then held), the dispatcher's own attributes after
        if name == "dispatcher":
            d = self.dispatcher = load().njit(cache=True, nogil=True)(self.py_func)
            return d
        if name.startswith("__") or name == "py_func":
            raise AttributeError(name)
        return getattr(self.dispatcher, name)

    def __reduce__(self):
        return self.dispatcher.__reduce__()

    def __repr__(self) -> str:
        return f"<motorctl.jit.Kernel {self.__module__}.{self.__qualname__}>"


def njit(py_func):
    """Decorator for the per-sample kernels: ``py_func`` compiled by numba in nopython mode,
    cached, no GIL needed, at its first use (a :class:`Kernel`); with ``NUMBA_DISABLE_JIT=1``,
    ``py_func`` itself.

    (A constant argument from a compiled caller gives the callee an overload of its own, numba's
    literal typing: 9 of ``sup_trip`` in the servo cycle, 3 of ``_matrix``. Compiling once per
    argument types instead saved those overloads at a cold start but made the compiled call of a
    cycle about 4 % slower (C2, both axes: 1.75 against 1.68 us): the callees lost their
    constants.)
    """
    return py_func if DISABLED else Kernel(py_func)


def dispatcher_of(kernel):
    """numba's dispatcher of ``kernel`` (a :class:`Kernel`; compiled or loaded now), for a call
    from Python on a hot path: the :class:`Kernel` in front of it costs 70-150 ns a call more
    (the loop's heartbeat, once a cycle). With the JIT disabled (or for a function that is not
    a Kernel), ``kernel`` itself."""
    return kernel.dispatcher if isinstance(kernel, Kernel) else kernel


def _define_bundle_type():
    nb = load()

    class BundleType(nb.types.StructRef):
        """Base of the bundles' numba types: the field types as given (no literal types)."""

        def preprocess_fields(self, fields):
            return tuple((name, nb.types.unliteral(t)) for name, t in fields)

    BundleType.__module__, BundleType.__qualname__ = __name__, "BundleType"
    return BundleType


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
    structref = load().structref
    structref.register(type_cls)
    structref.define_constructor(proxy_cls, type_cls, list(fields))
    structref.define_boxing(type_cls, proxy_cls)


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
    typeof = load().typeof
    return kernel.compile(tuple(typeof(a) for a in args))


def _borrow_py(a):
    return a


def _define_borrow():
    nb = load()

    @nb.intrinsic
    def _borrow_jit(typingctx, arr):
        if not isinstance(arr, nb.types.Array):
            return None

        def codegen(context, builder, signature, args):
            view = context.make_array(arr)(context, builder, value=args[0])
            view.meminfo = context.get_constant_null(nb.types.MemInfoPointer(arr.dtype))
            return view._getvalue()
        return arr(arr), codegen
    return _borrow_jit


#: ``borrow(a)``, in compiled code: the same array (data, shape, strides) without a reference to
#: its owner, so that numba counts no references for it, here or in the kernels it is passed to.
#: For views that live only inside the kernel that takes them, while the caller holds their
#: owner: a borrowed view must never be returned, stored in a bundle or outlive that call.
#: With the JIT disabled, the array itself. (With the JIT, numba's intrinsic is created at the
#: name's first import, :func:`__getattr__`: numba types an intrinsic by the object itself, so no
#: :class:`Kernel` can stand in for it.)
if DISABLED:
    borrow = _borrow_py

#: the names whose definition imports numba, defined at their first import (:func:`__getattr__`)
_ON_FIRST_USE = {"BundleType": _define_bundle_type, "borrow": _define_borrow}


def __getattr__(name):
    """``BundleType`` and (with the JIT) ``borrow``: numba's types, defined at their first import."""
    make = _ON_FIRST_USE.get(name)
    if make is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = globals()[name] = make()
    return value


def dispatch(kernels, otherwise):
    """A compiled ``call(c, *args)``: ``kernel(*args)`` for the code c of a pair (c, kernel) of
    ``kernels``, else ``otherwise(c, *args)`` (a kernel too). The one way a table of compiled kernels is called by
    code (:mod:`motorctl.effects.plant`, :mod:`motorctl.effects.compensation`): the if-chain
    over the codes is built here from the table, so that a kernel is added in the table only.

    Each link is a small compiled function with its kernel and the next link bound in its
    closure (called, never passed as a value: numba caches a function that calls a kernel, not
    one that holds a kernel as a value); LLVM inlines the chain into the caller. With the JIT
    disabled, the same functions in Python.

    Args:
        kernels: (code (int), kernel) pairs: the compiled kernels (:data:`njit`), all taking the
            same arguments, by code.
        otherwise: compiled ``otherwise(c, *args)``, called for a code outside the table (its
            result is the call's, e.g. NaN so that the caller's output faults).
    """
    call = otherwise
    for code, kernel in reversed(list(kernels)):
        call = _link(int(code), kernel, call)
    return call


def check_code(table, code, kind: str, what: str) -> int:
    """``code`` when ``table[code]`` (a table of (kind, kernel) rows, as :func:`dispatch`'s
    callers keep) is a ``kind`` kernel.

    Raises:
        ValueError: an unknown code or one of another kind: "``what`` code C is not a compiled
            ``kind`` kernel; known: ..." naming every row.
    """
    if (isinstance(code, bool) or not isinstance(code, int) or not 0 <= code < len(table)
            or table[code][0] != kind):
        known = ", ".join(f"{i} ({k} {fn.__name__})" for i, (k, fn) in enumerate(table))
        raise ValueError(f"{what} code {code!r} is not a compiled {kind!r} kernel; known: {known}")
    return code


@njit
def copy_into(dst, src):
    """``dst[...] = src`` for two arrays of the same shape and dtype (any number of dimensions);
    a different shape copies nothing. In compiled code, without the slice assignment's shape
    check, whose error message alone (numba's string formatting) took a third of the compile
    time of the state copies of the loop's rehearsal."""
    if dst.shape == src.shape:
        for idx in np.ndindex(src.shape):
            dst[idx] = src[idx]


def _link(code, kernel, rest):
    def call(c, *args):
        if c == code:
            return kernel(*args)
        return rest(c, *args)
    return njit(call)
