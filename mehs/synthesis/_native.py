"""The one-pass merge kernels' machine code, kept and loaded without numba (issue 16).

A warm ``mehs fuse`` spent 0.4–0.7 s of its ~1.4 s starting numba: importing it and
setting up its CPU target before it could load a cached kernel, holding the GIL
while the linearity test ran. The merge needs none of numba's machinery at run
time, only the kernel's machine code. So the first merge of a kind (kernel, raw
dtype, number of exposures) compiles a C-callable entry point around the numba
kernel (``numba.cfunc``), keeps its object code in ``<cache>/kernels/`` and later
processes load it straight into LLVM's JIT linker through llvmlite (tens of ms) and
call it through ctypes, which releases the GIL as the numba kernel did. The
numbers are the numba kernel's: it is the same compiled code (tested to the bit).

The key of a stored object covers every input of the compilation: the source of
the kernel modules and of this one, the numba and llvmlite versions, the host CPU
and its features, numba's CPU overrides, Python's version, the raw dtype and the
number of exposures. An object whose recorded SHA-256 does not match, or that needs
a symbol this process cannot give it, is not loaded: the merge compiles it anew
(or, if that fails, runs the numba kernel). The symbols numba's error handling
refers to (raising a Python exception from compiled code) are bound to ``abort``:
the kernels cannot raise (``error_model="numpy"``, no bounds checks, no allocation),
so those paths are dead; were one ever reached, the process stops loudly rather
than returning a wrong number.

The cache folder is :func:`mehs._cache.cache_dir`'s (``MEHS_CACHE_DIR``; empty: no
stored objects, the merge uses numba's dispatcher as before).
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import json
import os
import sys
import threading
from pathlib import Path
from typing import Callable

import numpy as np

#: Bumped when the stored layout or the entry points' C signatures change.
FORMAT = "mehs-native-kernel/1"

#: kernel name → (module, function, extra scalar arguments between ``times`` and ``gain``)
KERNELS = {
    "poisson_linear": ("mehs.synthesis._merge_fused", "merge_chunk_poisson_linear", ()),
    "debevec_linear": ("mehs.synthesis._merge_fused_weighted", "merge_chunk_debevec_linear",
                       (("L", "int64"), ("floor", "float32"))),
    "robertson_linear": ("mehs.synthesis._merge_fused_weighted", "merge_chunk_robertson_linear",
                         (("L", "int64"), ("floor", "float32"))),
    "invvar_linear": ("mehs.synthesis._merge_fused_weighted", "merge_chunk_invvar_linear",
                      (("L", "int64"), ("floor", "float32"))),
}
#: the sources whose text enters every key (the kernels, what they import, this module)
_SOURCES = ("_merge_fused.py", "_merge_fused_weighted.py", "_merge_rows.py", "_cephes.py",
            "_native.py")
#: numba's error-path helpers (see the module docstring)
_DEAD_SYMBOLS = frozenset({
    "NRT_Free", "NRT_MemInfo_call_dtor", "NRT_decref", "NRT_incref", "numba_do_raise",
    "numba_gil_ensure", "numba_gil_release", "numba_runtime_build_excinfo_struct",
    "numba_unpickle"})
#: raw dtypes with a stored entry point (others run the numba kernel)
_DTYPES = ("uint8", "uint16", "int16", "int32", "uint32", "float32", "float64")
_MAX_EXPOSURES = 16

_lock = threading.Lock()
_loaded: dict[tuple, Callable | None] = {}
_engines: list = []          # the JIT engines own the loaded code: kept for the process
_key_base: dict | None = None


def _folder() -> Path | None:
    from mehs._cache import cache_dir

    root = cache_dir()
    return None if root is None else root / "kernels"


def _base_key() -> dict:
    """What every stored object depends on besides its kernel, dtype and exposure count."""
    global _key_base
    if _key_base is None:
        from importlib.metadata import version

        import llvmlite
        import llvmlite.binding as ll

        here = Path(__file__).resolve().parent
        h = hashlib.sha256()
        for name in _SOURCES:
            h.update(name.encode() + b"\0" + (here / name).read_bytes() + b"\0")
        _key_base = {
            "format": FORMAT, "sources": h.hexdigest(), "numba": version("numba"),
            "llvmlite": llvmlite.__version__, "python": list(sys.version_info[:2]),
            "cpu": ll.get_host_cpu_name(), "features": ll.get_host_cpu_features().flatten(),
            "env": {k: os.environ.get(k, "") for k in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES",
                                                        "NUMBA_OPT", "NUMBA_BOUNDSCHECK")},
        }
    return _key_base


def _key(kind: str, dtype: np.dtype, P: int) -> tuple[dict, str]:
    key = dict(_base_key(), kernel=kind, dtype=dtype.name, exposures=P)
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:24]
    return key, f"{kind}-{dtype.name}-P{P}-{digest}"


def supported(kind: str, dtype, P: int) -> bool:
    """Whether a stored entry point can exist for this merge (else: the numba kernel).

    Native byte order only: the entry point reads the raw buffer as the machine does.
    """
    dtype = np.dtype(dtype)
    return (kind in KERNELS and dtype.name in _DTYPES and dtype.isnative
            and 2 <= P <= _MAX_EXPOSURES and _folder() is not None)


def native_kernel(kind: str, dtype, P: int, *, build: bool = True) -> Callable | None:
    """The kernel ``kind`` for ``P`` exposures of raw ``dtype``, as a Python callable.

    Takes the numba kernel's arguments (``zs`` a tuple of C-contiguous arrays; every
    array C-contiguous, of the kernel's dtypes: anything else raises ``TypeError``).
    Loaded from the cache without importing numba; with ``build``, compiled and stored
    when missing. None when there is no cache folder, the combination is not
    supported, or compiling failed: the caller runs the numba kernel.
    """
    dtype = np.dtype(dtype)
    if not supported(kind, dtype, P):
        return None
    memo = (kind, dtype.name, P, str(_folder()))
    with _lock:
        if memo in _loaded and (_loaded[memo] is not None or not build):
            return _loaded[memo]
        fn = _load(kind, dtype, P)
        if fn is None and build:
            fn = _build(kind, dtype, P)
        if fn is not None or build:
            _loaded[memo] = fn
        return fn


def is_stored(kind: str, dtype, P: int) -> bool:
    """Whether the cache holds a loadable entry point (for the first-compile notice)."""
    return native_kernel(kind, dtype, P, build=False) is not None


# -- loading ----------------------------------------------------------------------

def _load(kind: str, dtype: np.dtype, P: int) -> Callable | None:
    folder = _folder()
    try:
        key, stem = _key(kind, dtype, P)
    except Exception:       # noqa: BLE001 - no llvmlite, no metadata: use numba
        return None
    meta_path, obj_path = folder / f"{stem}.json", folder / f"{stem}.o"
    try:
        meta = json.loads(meta_path.read_text())
        obj = obj_path.read_bytes()
    except (OSError, ValueError):
        return None
    if (not isinstance(meta, dict) or meta.get("key") != key
            or meta.get("sha256") != hashlib.sha256(obj).hexdigest()
            or not isinstance(meta.get("symbol"), str)
            or not isinstance(meta.get("undefined"), list)):
        return None
    try:
        return _link(kind, dtype, P, obj, meta["symbol"], meta["undefined"])
    except Exception:       # noqa: BLE001 - no ctypes libc, an llvmlite error: use numba
        return None


def _abort_address() -> int:
    return ctypes.cast(ctypes.CDLL(None).abort, ctypes.c_void_p).value


def _link(kind: str, dtype: np.dtype, P: int, obj: bytes, symbol: str,
          undefined: list) -> Callable | None:
    # LLVM's global context is not thread-safe: where numba is loaded (a recovered
    # curve's kernels may be compiling on another thread) link under its compiler lock
    lock = contextlib.nullcontext()
    if "numba" in sys.modules:
        from numba.core.compiler_lock import global_compiler_lock as lock
    with lock:
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


def _wrap(kind: str, dtype: np.dtype, P: int, address: int) -> Callable:
    """A callable with the numba kernel's arguments over the C entry point at ``address``."""
    extra = KERNELS[kind][2]
    vp = ctypes.c_void_p
    ctype = {"int64": ctypes.c_int64, "float32": ctypes.c_float}
    argtypes = ([vp] * P + [vp, vp, vp] + [ctype[t] for _, t in extra]
                + [ctypes.c_double, vp, ctypes.c_double, vp, ctypes.c_bool, ctypes.c_bool,
                   ctypes.c_int64, ctypes.c_int64, ctypes.c_int64] + [vp] * 7)
    # CFUNCTYPE (not PYFUNCTYPE): the call releases the GIL, as the nogil kernel did
    entry = ctypes.CFUNCTYPE(None, *argtypes)(address)
    n_extra = len(extra)
    out_dtypes = (np.float32, np.float32, np.int32, np.float32, np.int32, np.int32, np.float32)

    def ptr(a, dtype, shape, what):
        if not (isinstance(a, np.ndarray) and a.dtype == dtype and a.flags.c_contiguous
                and a.shape == shape):
            raise TypeError(f"native merge kernel: {what} must be a C-contiguous {np.dtype(dtype)} "
                            f"array of shape {shape}")
        return a.ctypes.data

    dtype = np.dtype(dtype.name)          # native byte order (see supported)

    def call(zs, darks, sat, times, *rest):
        scalars, rest = rest[:n_extra], rest[n_extra:]
        gain, avar, rel_var, cal, want_chi2, clip, *outs = rest
        if len(zs) != P or len(outs) != 7:
            raise TypeError(f"native merge kernel: {P} exposures and 7 outputs expected")
        out = outs[0]
        nl, nb, ns = out.shape
        zp = [ptr(z, dtype, (nl, nb, ns), f"exposure {j}") for j, z in enumerate(zs)]
        args = zp + [ptr(darks, np.float32, (P, nb, ns), "darks"),
                     ptr(sat, np.float32, (nb,), "sat"), ptr(times, np.float32, (P,), "times")]
        args += [int(s) if t == "int64" else float(s) for s, (_, t) in zip(scalars, extra)]
        args += [float(gain), ptr(avar, np.float32, (P,), "avar"), float(rel_var),
                 ptr(cal, np.float32, (nb,), "cal"), bool(want_chi2), bool(clip), nl, nb, ns]
        args += [ptr(o, dt, (nl, nb, ns) if k == 0 else (nl, ns), f"output {k}")
                 for k, (o, dt) in enumerate(zip(outs, out_dtypes))]
        entry(*args)         # (the arrays stay referenced by the caller meanwhile)

    call.kind, call.exposures = kind, P
    return call


# -- building ---------------------------------------------------------------------

_TEMPLATE = '''
def entry({zargs}, dk, sat, times, {xargs}gain, avar, rel, cal, want, clip, nl, nb, ns,
          out, chi2, dof, snr, nsat, nvalid, msum):
    zs = ({zarrays},)
    K(zs, carray(dk, (P, nb, ns)), carray(sat, (nb,)), carray(times, (P,)), {xargs}gain,
      carray(avar, (P,)), rel, carray(cal, (nb,)), want, clip, carray(out, (nl, nb, ns)),
      carray(chi2, (nl, ns)), carray(dof, (nl, ns)), carray(snr, (nl, ns)),
      carray(nsat, (nl, ns)), carray(nvalid, (nl, ns)), carray(msum, (nl, ns)))
'''


def _writable(folder: Path) -> bool:
    """Whether entries can be stored in ``folder`` (created if missing)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)


def _build(kind: str, dtype: np.dtype, P: int) -> Callable | None:
    """Compile the C entry point with numba, store its object code, load it.

    Nothing is compiled when the cache folder cannot take the entry: every process
    would pay for a compile it cannot keep (the numba kernel runs instead, cached by
    numba where it can be).
    """
    folder = _folder()
    if folder is None or not _writable(folder):
        return None
    from mehs.synthesis._numba_cache import notice_compiling

    # a first-ever run compiles for seconds: say so instead of looking hung
    notice_compiling("the synthesis kernels")
    try:
        key, stem = _key(kind, dtype, P)
        obj, symbol, undefined = _compile(kind, dtype, P)
        from mehs.io.atomic import write_bytes_atomic, write_json_atomic

        write_bytes_atomic(folder / f"{stem}.o", obj)
        write_json_atomic(folder / f"{stem}.json",
                          {"key": key, "symbol": symbol, "undefined": undefined,
                           "sha256": hashlib.sha256(obj).hexdigest()})
    except Exception:       # noqa: BLE001 - anything: the numba kernel does the work
        return None
    return _load(kind, dtype, P)


def _compile(kind: str, dtype: np.dtype, P: int) -> tuple[bytes, str, list[str]]:
    """numba-compile the entry point: (object code, its symbol, the symbols it needs)."""
    import importlib

    import llvmlite.binding as ll
    from numba import carray, cfunc, types

    from mehs.synthesis._numba_start import skip_scipy_linalg_import

    skip_scipy_linalg_import()
    module, name, extra = KERNELS[kind]
    K = getattr(importlib.import_module(module), name)
    nbt = {"int64": types.int64, "float32": types.float32}
    f32p, i32p = types.CPointer(types.float32), types.CPointer(types.int32)
    zp = types.CPointer(getattr(types, dtype.name))
    sig = types.void(*([zp] * P), f32p, f32p, f32p, *[nbt[t] for _, t in extra],
                     types.float64, f32p, types.float64, f32p, types.boolean, types.boolean,
                     types.int64, types.int64, types.int64,
                     f32p, f32p, i32p, f32p, i32p, i32p, f32p)
    src = _TEMPLATE.format(
        zargs=", ".join(f"z{j}" for j in range(P)),
        zarrays=", ".join(f"carray(z{j}, (nl, nb, ns))" for j in range(P)),
        xargs="".join(f"{n}, " for n, _ in extra))
    ns_: dict = {"K": K, "carray": carray, "P": P}
    exec(compile(src, f"<mehs native entry {kind}>", "exec"), ns_)   # noqa: S102
    compiled = cfunc(sig, nogil=True, error_model="numpy")(ns_["entry"])
    _, _, (obj, bitcode) = compiled._library.serialize_using_object_code()
    mod = ll.parse_bitcode(bitcode)
    undefined = sorted({f.name for f in mod.functions
                        if f.is_declaration and not f.name.startswith("llvm.")}
                       | {g.name for g in mod.global_variables if g.is_declaration})
    return obj, compiled.native_name, undefined
