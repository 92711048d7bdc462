"""Compiled kernels' machine code, kept and loaded without numba (issue 16).

A warm ``mehs fuse`` spent 0.4–0.7 s of its ~1.4 s starting numba: importing it and
setting up its CPU target before it could load a cached kernel, holding the GIL
while the linearity test ran. Its kernels — the one-pass merges and the
photon-transfer passes of the noise model and linearity test — need none of numba's
machinery at run time, only their machine code. So the first use of a kind (kernel,
raw dtype, number of exposures) compiles a C-callable entry point around the numba
kernel (``numba.cfunc``), keeps its object code in ``<cache>/kernels/`` and later
processes load it straight into LLVM's JIT linker through llvmlite (tens of ms) and
call it through ctypes, which releases the GIL as the numba kernel did. The
numbers are the numba kernel's: the same source through the same compiler, at most
tuned differently (tested to the bit).
The kernels and their parameters are listed in :mod:`mehs.synthesis._native_specs`;
linking and calling an entry is :mod:`._native_link`, compiling it in a child process
(the host's widest vectors; LLVM options that vectorise brackets of more than 3
exposures) :mod:`._native_child`.

The key of a stored object covers every input of the compilation: the source of
the kernel modules, of this one and of the specs, the numba and llvmlite versions, the
host CPU and its features, numba's CPU overrides, Python's version, the raw dtype, the
number of exposures and the LLVM options. An object whose recorded SHA-256 does not
match, or that needs a symbol this process cannot give it, is not loaded: it is
compiled anew (or, if that fails, the numba kernel runs). The symbols numba's error
handling refers to (raising a Python exception from compiled code) are bound to
``abort``: the kernels cannot raise (``error_model="numpy"``, no bounds checks, no
allocation), so those paths are dead; were one ever reached, the process stops loudly
rather than returning a wrong number.

The cache folder is :func:`mehs._cache.cache_dir`'s (``MEHS_CACHE_DIR``; empty: no
stored objects, numba's dispatchers run as before).
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Callable

import numpy as np

from mehs.synthesis import _native_child
from mehs.synthesis._native_link import _TUPLES, flat_params, link
from mehs.synthesis._native_specs import KERNELS

#: Bumped when the stored layout or the entry points' C signatures change.
FORMAT = "mehs-native-kernel/2"

#: raw dtypes with a stored entry point (others run the numba kernel)
_DTYPES = ("uint8", "uint16", "int16", "int32", "uint32", "float32", "float64")
_MAX_EXPOSURES = 16

_memo_lock = threading.Lock()       # guards the dicts below
_build_locks: dict[tuple, threading.Lock] = {}   # one builder per entry point
_children: dict[tuple, subprocess.Popen] = {}    # entries compiling in a child process
_loaded: dict[tuple, Callable | None] = {}
_failed: set[tuple] = set()  # entries whose compile failed here: numba's kernel from then on
_key_base: dict | None = None
_in_child = False           # this process is a child compiling one entry (_child_build)
_linkable: bool | None = None   # _can_link's answer
_sources_digest: dict[tuple, str] = {}


def _folder() -> Path | None:
    from mehs._cache import cache_dir

    root = cache_dir()
    return None if root is None else root / "kernels"


def _base_key() -> dict:
    """What every stored object depends on besides its kernel, its sources, dtype and
    exposure count."""
    global _key_base
    if _key_base is None:
        import llvmlite
        import llvmlite.binding as ll

        _key_base = {
            "format": FORMAT, "numba": _numba_version(),
            "llvmlite": llvmlite.__version__, "python": list(sys.version_info[:2]),
            "cpu": ll.get_host_cpu_name(), "features": ll.get_host_cpu_features().flatten(),
            "env": {k: os.environ.get(k, "") for k in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES",
                                                        "NUMBA_OPT", "NUMBA_BOUNDSCHECK")},
            # the features the entries are compiled with beyond the host's (a child's)
            "tuning": _native_child.tuning(),
        }
    return _key_base


def _numba_version() -> str:
    """numba's version without importing numba: from the version file of its package
    (versioneer's ``_version.py``), else its distribution's metadata — whose lookup scans
    every installed distribution, 20–25 ms of every warm ``mehs fuse`` (issue 16)."""
    import importlib.util
    import re

    try:
        spec = importlib.util.find_spec("numba")
        text = Path(spec.origin).with_name("_version.py").read_text(encoding="utf-8")
        # a release's file holds the JSON that versioneer wrote at build time; a source
        # checkout's computes the version from git (its literals say "0+unknown")
        block = re.search(r"^version_json = '{3}\n(.*?)'{3}", text, re.S | re.M)
        got = json.loads(block.group(1)) if block else {}
        found = got.get("version") if isinstance(got, dict) and not got.get("error") else None
        if isinstance(found, str) and found and not found.startswith("0+"):
            return found
    except (ImportError, AttributeError, TypeError, ValueError, OSError):
        pass
    from importlib.metadata import version

    return version("numba")


def _sources(kind: str) -> str:
    """SHA-256 of the kernel's source files, of this module and of the specs."""
    names = KERNELS[kind].sources + ("_native.py", "_native_specs.py", "_native_child.py",
                                     "_native_link.py")
    if names not in _sources_digest:
        here = Path(__file__).resolve().parent
        h = hashlib.sha256()
        for name in names:
            h.update(name.encode() + b"\0" + (here / name).read_bytes() + b"\0")
        _sources_digest[names] = h.hexdigest()
    return _sources_digest[names]


def _key(kind: str, dtype: np.dtype, P: int) -> tuple[dict, str]:
    key = dict(_base_key(), sources=_sources(kind), kernel=kind, dtype=dtype.name, exposures=P,
               llvm=list(_native_child.llvm_options(P)))
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:24]
    return key, f"{kind}-{dtype.name}-P{P}-{digest}"


def supported(kind: str, dtype, P: int = 0) -> bool:
    """Whether a stored entry point can exist for this kernel (else: the numba kernel).

    ``P``: the number of exposures of a merge kernel (2 … 16), 0 for the others.
    Native byte order only: the entry point reads the raw buffer as the machine does.
    """
    dtype = np.dtype(dtype)
    if kind not in KERNELS:
        return False
    ok_P = 2 <= P <= _MAX_EXPOSURES if KERNELS[kind].per_exposure else P == 0
    return (ok_P and dtype.name in _DTYPES and dtype.isnative and _folder() is not None
            and _can_link())


def _can_link() -> bool:
    """Whether this process can bind a stored entry's symbols (the process's own, through
    ``ctypes.CDLL(None)``: not on Windows). Where it cannot, every process would compile
    an entry it can never load."""
    global _linkable
    if _linkable is None:
        try:
            ctypes.CDLL(None)
            _linkable = True
        except (OSError, TypeError):
            _linkable = False
    return _linkable


def native_kernel(kind: str, dtype, P: int = 0, *, build: bool = True) -> Callable | None:
    """The kernel ``kind`` (for ``P`` exposures) of raw ``dtype``, as a Python callable.

    Takes the numba kernel's arguments (a merge's ``zs`` a tuple of arrays; every array
    C-contiguous, of the kernel's dtypes and shapes: anything else raises ``TypeError``).
    Loaded from the cache without importing numba; with ``build``, compiled and stored
    when missing. None when there is no cache folder, the combination is not
    supported, or compiling failed: the caller runs the numba kernel.
    """
    dtype = np.dtype(dtype)
    if not supported(kind, dtype, P):
        return None
    memo = (kind, dtype.name, P, str(_folder()))

    def settled() -> bool:
        # loaded, or tried here: a None from a build=False call does not stop a build
        return memo in _loaded and (_loaded[memo] is not None or not build or memo in _failed)

    with _memo_lock:
        if settled():
            return _loaded[memo]
        child = _children.pop(memo, None)
        build_lock = _build_locks.setdefault(memo, threading.Lock())
    if child is not None:           # compiling in a child process: its entry is loaded
        try:
            child.wait(timeout=600)
        except subprocess.TimeoutExpired:
            child.kill()
    # (a build holds only its own entry's lock: another entry meanwhile loads, or
    # builds in a child process)
    with build_lock:
        with _memo_lock:
            if settled():
                return _loaded[memo]
        fn = _load(kind, dtype, P)
        failed = False
        if fn is None and build:
            fn, failed = _build(kind, dtype, P)
        with _memo_lock:
            if fn is not None or build:
                _loaded[memo] = fn
            if failed:
                # not again in this process: a compile takes seconds (a child's too)
                _failed.add(memo)
        return fn


def build_in_background(kind: str, dtype, P: int = 0) -> bool:
    """Start compiling ``kind``'s entry point in a child process when none is stored.

    numba compiles one function at a time in a process: a first-ever ``mehs fuse``
    compiled the photon-transfer passes after the merge kernel (2 s + 2.5 s, one core
    idle). The child runs at a lower priority and outlives its parent if need be: a
    caller with another way to do the work (:func:`building`) goes on without it, and
    the entry is there for the next process. A later :func:`native_kernel` of the same
    entry waits for the child and loads what it stored (or, if it failed, builds as
    usual). The child holds a lock on ``<entry>.building`` in the cache folder while it
    compiles, so that another process neither starts a second one nor waits. True if a
    child was started.
    """
    dtype = np.dtype(dtype)
    if not supported(kind, dtype, P):
        return False
    memo = (kind, dtype.name, P, str(_folder()))
    files = _entry_files(kind, dtype, P)
    if files is None:
        return False        # no llvmlite: nothing to build
    meta, marker = files
    try:
        if meta.is_file() or not _writable(meta.parent):
            return False    # stored (checked when loaded), or nowhere to store it
    except OSError:         # a cache folder this user cannot enter
        return False
    if _native_child.locked_elsewhere(marker):
        return False        # another process's child is compiling it
    with _memo_lock:        # (one child per entry, whichever thread asks)
        if memo in _loaded or memo in _children:
            return False
        try:
            # at a lower priority: the parent's own work (the merge kernel's compilation
            # on a first-ever run) comes first on a machine with few cores
            _children[memo] = _native_child.start(kind, dtype.name, P, marker,
                                                  _key(kind, dtype, P)[0], background=True)
        except OSError:
            return False
    return True


#: Seconds a foreground child waits for another process's child to finish the same
#: entry (a compile takes seconds); then it compiles regardless (writes are atomic).
LOCK_WAIT_S = 120.0


def _child_build(kind: str, dtype: np.dtype, P: int, marker: str, key: dict, *,
                 wait: bool) -> None:
    """A child process of :mod:`._native_child`: compile and store the entry under the
    parent's ``key``, holding an exclusive lock on ``marker``. Another child holding it:
    a background child leaves; a waiting one waits (at most :data:`LOCK_WAIT_S`), then
    loads what that one stored, or compiles it. Nothing is built when this process's
    own key differs from the parent's but for its environment and tuning (another
    numba, sources changed since the parent read them): the parent's kernel arguments
    might not be this code's."""
    global _key_base, _in_child
    # its own numba, llvmlite, Python, host and sources must be those the key names (a
    # child may import another numba than its parent); its features and environment
    # differ by design
    own, _ = _key(kind, dtype, P)
    if any(own.get(k) != key.get(k) for k in own if k not in ("env", "tuning")):
        return
    _key_base = {k: v for k, v in key.items()
                 if k not in ("sources", "kernel", "dtype", "exposures")}
    _in_child = True
    _native_child.apply_llvm_options(key.get("llvm"))
    try:
        import fcntl
    except ImportError:     # not POSIX: no marker
        native_kernel(kind, dtype, P)
        return
    import time

    fd = os.open(marker, os.O_CREAT | os.O_RDWR, 0o644)
    deadline = time.monotonic() + (LOCK_WAIT_S if wait else 0.0)
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except OSError:
            if time.monotonic() >= deadline:
                if not wait:
                    return          # another child is compiling it
                break               # stuck elsewhere: compile without the lock
            time.sleep(0.05)
    native_kernel(kind, dtype, P)       # (the lock goes with the process)


def building(kind: str, dtype, P: int = 0) -> bool:
    """Whether ``kind``'s entry point is being compiled in a child process — this one's
    (:func:`build_in_background`) or another process's — and is not stored yet: a
    caller with another way to do the work need not wait for it."""
    dtype = np.dtype(dtype)
    memo = (kind, dtype.name, P, str(_folder()))
    with _memo_lock:
        if _loaded.get(memo) is not None:
            return False
        child = _children.get(memo)
    if child is not None and child.poll() is None:
        return True
    files = _entry_files(kind, dtype, P) if supported(kind, dtype, P) else None
    try:
        return (files is not None and not files[0].is_file()
                and _native_child.locked_elsewhere(files[1]))
    except OSError:         # a cache folder this user cannot enter
        return False


def _entry_files(kind: str, dtype: np.dtype, P: int) -> tuple[Path, Path] | None:
    """The stored entry's metadata file and its child's ``.building`` lock file in the
    cache folder (None without llvmlite to key them)."""
    try:
        _, stem = _key(kind, dtype, P)
    except Exception:       # noqa: BLE001 - no llvmlite, no metadata
        return None
    folder = _folder()
    return folder / f"{stem}.json", folder / f"{stem}.building"


def is_stored(kind: str, dtype, P: int = 0) -> bool:
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
        return link(kind, dtype, P, obj, meta["symbol"], meta["undefined"])
    except Exception:       # noqa: BLE001 - no ctypes libc, an llvmlite error: use numba
        return None


# -- building ---------------------------------------------------------------------

def _writable(folder: Path) -> bool:
    """Whether entries can be stored in ``folder`` (created if missing)."""
    from mehs._cache import writable_folder

    return writable_folder(folder)


def _build(kind: str, dtype: np.dtype, P: int) -> tuple[Callable | None, bool]:
    """Compile the C entry point with numba, store its object code, load it.

    Returns ``(entry or None, whether a compile was tried and failed)``. Nothing is
    compiled when the cache folder cannot take the entry: every process would pay for
    a compile it cannot keep (the numba kernel runs instead, cached by numba where it
    can be).
    """
    folder = _folder()
    if folder is None or not _writable(folder):
        return None, False
    from mehs.synthesis._numba_cache import notice_compiling

    # a first-ever run compiles for seconds: say so instead of looking hung
    notice_compiling("the synthesis kernels")
    try:
        key, stem = _key(kind, dtype, P)
        if (key["tuning"] or key["llvm"]) and not _in_child:
            fn = _build_in_child(kind, dtype, P, key)
            return fn, fn is None
        obj, symbol, undefined = _compile(kind, dtype, P)
        from mehs.io.atomic import write_bytes_atomic, write_json_atomic

        write_bytes_atomic(folder / f"{stem}.o", obj)
        write_json_atomic(folder / f"{stem}.json",
                          {"key": key, "symbol": symbol, "undefined": undefined,
                           "sha256": hashlib.sha256(obj).hexdigest()})
    except Exception:       # noqa: BLE001 - anything: the numba kernel does the work
        return None, True
    fn = _load(kind, dtype, P)
    return fn, fn is None


def _build_in_child(kind: str, dtype: np.dtype, P: int, key: dict) -> Callable | None:
    """Compile the entry with the features of :func:`._native_child.tuning` and the LLVM
    options of :func:`._native_child.llvm_options` in a child process (both are fixed
    for a whole process), wait, load it."""
    files = _entry_files(kind, dtype, P)
    if files is None:
        return None
    try:
        child = _native_child.start(kind, dtype.name, P, files[1], key, background=False)
    except OSError:
        return None
    try:
        child.wait(timeout=600)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()
        return None
    return _load(kind, dtype, P)


def _compile(kind: str, dtype: np.dtype, P: int) -> tuple[bytes, str, list[str]]:
    """numba-compile the entry point: (object code, its symbol, the symbols it needs)."""

    import llvmlite.binding as ll
    from numba import carray, cfunc, types

    from mehs.synthesis._numba_start import skip_scipy_linalg_import

    skip_scipy_linalg_import()
    spec = KERNELS[kind]
    K = spec.dispatcher()
    if _native_child.llvm_options(P):
        # from its source, whatever numba's own cache holds (a kernel it cached without the
        # options is linked as optimised IR and re-optimised: vectorised, by another route)
        from numba import njit

        K = njit(**{k: v for k, v in K.targetoptions.items() if k != "nopython"})(K.py_func)
    nbt = {"f4": types.float32, "f8": types.float64, "i4": types.int32, "i8": types.int64,
           "u1": types.uint8, "u2": types.uint16, "b1": types.boolean,
           "raw": getattr(types, dtype.name)}
    sig, c_names, flat_args = [], [], []
    for i, (_, t, nd) in enumerate(flat_params(kind, P)):
        # an array: its pointer and extents in, a carray over them to the kernel
        dims = [f"a{i}_{d}" for d in range(nd)]
        c_names += [f"a{i}", *dims]
        sig += [types.CPointer(nbt[t]) if nd else nbt[t]] + [types.int64] * nd
        flat_args.append(f"carray(a{i}, ({', '.join(dims)},))" if nd else f"a{i}")
    k_args = []           # a tuple parameter's P arrays regrouped into its tuple
    for _, t in spec.params:
        is_tuple = t.partition(":")[0] in _TUPLES
        n = P if is_tuple else 1
        group, flat_args = flat_args[:n], flat_args[n:]
        k_args.append(f"({', '.join(group)},)" if is_tuple else group[0])
    src = f"def entry({', '.join(c_names)}):\n    K({', '.join(k_args)})\n"
    ns_: dict = {"K": K, "carray": carray}
    exec(compile(src, f"<mehs native entry {kind}>", "exec"), ns_)   # noqa: S102
    compiled = cfunc(types.void(*sig), nogil=True, error_model="numpy")(ns_["entry"])
    _, _, (obj, bitcode) = compiled._library.serialize_using_object_code()
    mod = ll.parse_bitcode(bitcode)
    undefined = sorted({f.name for f in mod.functions
                        if f.is_declaration and not f.name.startswith("llvm.")}
                       | {g.name for g in mod.global_variables if g.is_declaration})
    return obj, compiled.native_name, undefined
