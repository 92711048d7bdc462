"""Linking a stored kernel's object code into this process and calling it (issue 16).

:mod:`mehs.synthesis._native` keeps the one-pass kernels' machine code; this module
binds an entry's undefined symbols (the process's own — libm, the Python C API — and
numba's error paths, bound to ``abort``: see that module's docstring), links the object
into LLVM's JIT through llvmlite and wraps the C entry point in a callable with the
numba kernel's arguments, checking every array before the unchecked compiled loops see
it.
"""

from __future__ import annotations

import contextlib
import ctypes
import sys
import threading
from typing import Callable

import numpy as np

from mehs.synthesis._native_specs import KERNELS

#: numba's error-path helpers (see :mod:`mehs.synthesis._native`'s docstring)
_DEAD_SYMBOLS = frozenset({
    "NRT_Free", "NRT_MemInfo_call_dtor", "NRT_decref", "NRT_incref", "numba_do_raise",
    "numba_gil_ensure", "numba_gil_release", "numba_runtime_build_excinfo_struct",
    "numba_unpickle"})
_link_lock = threading.Lock()       # LLVM's global context is not thread-safe
_engines: list = []          # the JIT engines own the loaded code: kept for the process


def _abort_address() -> int:
    return ctypes.cast(ctypes.CDLL(None).abort, ctypes.c_void_p).value


def link(kind: str, dtype: np.dtype, P: int, obj: bytes, symbol: str,
         undefined: list) -> Callable | None:
    # LLVM's global context is not thread-safe: where numba is loaded (a recovered
    # curve's kernels may be compiling on another thread) link under its compiler lock
    # (read off the module, never imported here: another thread may be importing numba
    # this moment, and importing its modules from two threads deadlocks; before that
    # module has made its lock, nothing can be compiling with numba)
    lock = getattr(sys.modules.get("numba.core.compiler_lock"), "global_compiler_lock", None)
    with lock or contextlib.nullcontext(), _link_lock:
        return _link_locked(kind, dtype, P, obj, symbol, undefined)


def _link_locked(kind: str, dtype: np.dtype, P: int, obj: bytes, symbol: str,
                 undefined: list) -> Callable | None:
    import llvmlite.binding as ll

    ll.initialize_native_target()
    ll.initialize_native_asmprinter()
    process = ctypes.CDLL(None)
    for name in undefined:
        if not isinstance(name, str):
            return None
        if ll.address_of_symbol(name):
            continue
        try:        # the process's own symbols (libm's sqrtf, the Python C API)
            address = ctypes.cast(getattr(process, name), ctypes.c_void_p).value
        except AttributeError:
            address = None
        if address:
            ll.add_symbol(name, address)
        elif name in _DEAD_SYMBOLS:
            ll.add_symbol(name, _abort_address())
        else:
            # LLVM's linker would end the process on an unresolved symbol: do not load
            return None
    target = ll.Target.from_default_triple()
    tm = target.create_target_machine(cpu=ll.get_host_cpu_name(),
                                      features=ll.get_host_cpu_features().flatten(),
                                      opt=3, codemodel="jitdefault")
    engine = ll.create_mcjit_compiler(ll.parse_assembly(""), tm)
    engine.add_object_file(ll.ObjectFileRef.from_data(obj))
    engine.finalize_object()
    address = engine.get_function_address(symbol)
    if not address:
        return None
    _engines.append(engine)
    return _wrap(kind, dtype, P, address)


_CTYPES = {"f4": ctypes.c_float, "f8": ctypes.c_double, "i8": ctypes.c_int64,
           "b1": ctypes.c_bool}
_NP = {"f4": np.float32, "f8": np.float64, "i4": np.int32, "i8": np.int64, "u1": np.uint8,
       "u2": np.uint16}


#: tuple parameters (one array per exposure) and their arrays' type
_TUPLES = {"zs": "raw", "f4s": "f4"}


def flat_params(kind: str, P: int) -> list[tuple[str, str, int]]:
    """The entry point's parameters: ``(name, type, ndim)``, ``ndim > 0`` for an array (its
    pointer, then ``ndim`` int64 extents), 0 for a scalar; a tuple parameter's arrays (a
    merge's exposures, its per-exposure scratch rows) one by one."""
    out = []
    for name, t in KERNELS[kind].params:
        base, _, nd = t.partition(":")
        if base in _TUPLES:
            what = "exposure" if base == "zs" else name
            out += [(f"{what} {j}", _TUPLES[base], int(nd)) for j in range(P)]
        else:
            out.append((name, base, int(nd or 0)))
    return out


def _flatten(spec, P: int, args, label: str) -> list:
    """The kernel's arguments with each tuple parameter's P arrays spread out."""
    values = []
    for (name, t), a in zip(spec.params, args):
        if t.partition(":")[0] in _TUPLES:
            if len(a) != P:
                what = "exposures" if name == "zs" else f"arrays in {name}"
                raise TypeError(f"native {label} kernel: {P} {what} expected, got {len(a)}")
            values += list(a)
        else:
            values.append(a)
    return values


def _wrap(kind: str, dtype: np.dtype, P: int, address: int) -> Callable:
    """A callable with the numba kernel's arguments over the C entry point at ``address``."""
    spec = KERNELS[kind]
    flat = flat_params(kind, P)
    argtypes = []
    for _, t, nd in flat:
        argtypes += [ctypes.c_void_p] + [ctypes.c_int64] * nd if nd else [_CTYPES[t]]
    # CFUNCTYPE (not PYFUNCTYPE): the call releases the GIL, as the nogil kernel did
    entry = ctypes.CFUNCTYPE(None, *argtypes)(address)
    dtype = np.dtype(dtype.name)          # native byte order (see supported)
    label = "merge" if spec.per_exposure else kind
    n_params = len(spec.params)

    def call(*args):
        if len(args) != n_params:
            raise TypeError(f"native {label} kernel: {n_params} arguments expected")
        values = _flatten(spec, P, args, label)
        c_args = []
        for (name, t, nd), a in zip(flat, values):
            if not nd:
                if t == "i8":
                    # ctypes wraps an int64 silently (2**64 + 1 arrives as 1): a
                    # checked step or index would not be the one the loop runs with
                    a = int(a)
                    if not -2 ** 63 <= a < 2 ** 63:
                        raise TypeError(f"native {label} kernel: {name} = {a} is not an int64")
                c_args.append(a if t == "i8" else bool(a) if t == "b1" else float(a))
                continue
            want = dtype if t == "raw" else np.dtype(_NP[t])
            if not (isinstance(a, np.ndarray) and a.dtype == want and a.flags.c_contiguous
                    and a.ndim == nd):
                raise TypeError(f"native {label} kernel: {name} must be a C-contiguous "
                                f"{want} array of {nd} dimension(s)")
            written = name in spec.writes or name.rsplit(" ", 1)[0] in spec.writes
            if written and not a.flags.writeable:
                # (numba's dispatcher refuses a read-only array it writes to)
                raise TypeError(f"native {label} kernel: {name} must be writeable")
            c_args += [a.ctypes.data, *a.shape]
        spec.check(P, args)
        entry(*c_args)         # (the arrays stay referenced by the caller meanwhile)

    call.kind, call.exposures = kind, P
    return call
