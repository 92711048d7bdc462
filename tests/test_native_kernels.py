"""The merge kernels' stored machine code, loaded without numba (issue 16).

:mod:`mehs.synthesis._native` compiles a C entry point around each one-pass kernel
once, keeps its object code in the mehs cache and links it into later processes
through llvmlite. Its numbers must be numba's own kernel's to the bit, a damaged or
foreign cache entry must never be loaded, and a warm process must not start numba.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _checks import assert_same_merge_bits

from mehs.synthesis.merge import NoiseModel, merge_bracket

ROOT = Path(__file__).resolve().parents[1]


def _bracket(P, dtype=np.uint16, seed=0):
    rng = np.random.default_rng(seed)
    E = np.exp(rng.uniform(np.log(0.2), np.log(3000), (9, 17, 6)))
    t = [1.0, 4.0, 16.0, 64.0][:P]
    stack = []
    for j, tj in enumerate(t):
        x = E * tj + 60 + rng.normal(0, 4, E.shape)
        if j == P - 1:
            x[:2, :4] += 5000                       # a ghost: censored samples
        stack.append(np.clip(np.rint(x), 0, 4095).astype(dtype))
    darks = [np.full((17, 6), 60.0) + rng.normal(0, 1, (17, 6)) for _ in range(P)]
    return stack, t, darks


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "kernels"


@pytest.mark.parametrize("method,P,dtype,consistency", [("poisson", 3, np.uint16, True),
                                                        ("debevec", 2, np.int16, True),
                                                        ("inverse-variance", 4, np.uint16, False)])
def test_stored_kernel_gives_the_numba_kernels_bits(cache, monkeypatch, method, P, dtype,
                                                    consistency):
    from mehs.synthesis import _native

    stack, t, darks = _bracket(P, dtype)
    kw = dict(method=method, darks=darks, noise=NoiseModel(1.5, 3.0, relative=0.01),
              consistency=consistency)
    stored = merge_bracket(stack, t, **kw)
    kind = {"poisson": "poisson_linear", "debevec": "debevec_linear",
            "inverse-variance": "invvar_linear"}[method] + ("" if consistency else "_radiance")
    assert _native.is_stored(kind, dtype, P)                    # the native path ran
    assert len(list(cache.glob(f"{kind}-*.o"))) == 1
    monkeypatch.setenv("MEHS_CACHE_DIR", "")                    # numba's dispatcher
    assert_same_merge_bits(stored, merge_bracket(stack, t, **kw))


def test_a_warm_process_merges_without_starting_numba(cache):
    stack, t, darks = _bracket(3)
    folder = cache.parent.parent
    np.save(folder / "stack.npy", np.stack(stack))
    code = (
        "import sys, numpy as np\n"
        "from mehs.synthesis.merge import merge_bracket\n"
        f"s = np.load({str(folder / 'stack.npy')!r})\n"
        f"r = merge_bracket(list(s), {t!r}, darks=[np.full((17, 6), 60.0)] * 3)\n"
        f"np.save({str(folder / 'out.npy')!r}, np.asarray(r.radiance))\n"
        "print('NUMBA', 'numba' in sys.modules)\n")
    env = dict(os.environ, MEHS_CACHE_DIR=str(cache.parent), PYTHONPATH=str(ROOT))
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env=env, timeout=600) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    assert "compiling the synthesis kernels once" in runs[0].stderr
    assert "NUMBA False" in runs[1].stdout, runs[1].stdout + runs[1].stderr
    assert "compiling" not in runs[1].stderr
    ref = merge_bracket(stack, t, darks=[np.full((17, 6), 60.0)] * 3)
    np.testing.assert_array_equal(np.load(folder / "out.npy"), np.asarray(ref.radiance))


def _reset(monkeypatch):
    from mehs.synthesis import _native

    monkeypatch.setattr(_native, "_loaded", {})


@pytest.mark.parametrize("damage", ["flip a byte", "truncate", "bad json", "other key"])
def test_a_damaged_or_foreign_entry_is_never_loaded(cache, monkeypatch, damage):
    """A stored object is loaded only with its recorded key and SHA-256: anything else is
    compiled anew (a damaged object handed to LLVM could end the process)."""
    from mehs.synthesis import _native

    stack, t, darks = _bracket(3)
    first = merge_bracket(stack, t, darks=darks)
    obj = next(cache.glob("poisson_linear-uint16-P3-*.o"))
    meta = obj.with_suffix(".json")
    if damage == "flip a byte":
        b = bytearray(obj.read_bytes())
        b[len(b) // 2] ^= 0xFF
        obj.write_bytes(bytes(b))
    elif damage == "truncate":
        obj.write_bytes(obj.read_bytes()[:100])
    elif damage == "bad json":
        meta.write_text("{not json")
    else:
        m = json.loads(meta.read_text())
        m["key"]["llvmlite"] = "0.0.0"
        meta.write_text(json.dumps(m))
    _reset(monkeypatch)
    assert not _native.is_stored("poisson_linear", np.uint16, 3)
    assert_same_merge_bits(first, merge_bracket(stack, t, darks=darks))    # compiled anew
    assert _native.is_stored("poisson_linear", np.uint16, 3)
    _reset(monkeypatch)
    assert _native.is_stored("poisson_linear", np.uint16, 3)    # and stored again


def test_an_entry_needing_an_unknown_symbol_is_not_linked(cache, monkeypatch):
    from mehs.synthesis import _native

    stack, t, darks = _bracket(3)
    merge_bracket(stack, t, darks=darks)
    meta = next(cache.glob("poisson_linear-uint16-P3-*.json"))
    m = json.loads(meta.read_text())
    m["undefined"].append("mehs_no_such_symbol_anywhere")
    meta.write_text(json.dumps(m))
    _reset(monkeypatch)
    assert _native.native_kernel("poisson_linear", np.uint16, 3, build=False) is None


def test_the_entry_point_refuses_arrays_it_cannot_read_as_the_kernel_does(cache):
    from mehs.synthesis import _native

    stack, t, darks = _bracket(3)
    merge_bracket(stack, t, darks=darks)
    call = _native.native_kernel("poisson_linear", np.uint16, 3)
    nl, nb, ns = 2, 6, 17
    zs = tuple(np.zeros((nl, nb, ns), np.uint16) for _ in range(3))
    args = [np.zeros((3, nb, ns), np.float32), np.full(nb, 4000, np.float32),
            np.array(t, np.float32), 1.0, np.ones(3, np.float32), 0.0, np.ones(nb, np.float32),
            True, True]
    outs = [np.zeros((nl, nb, ns), np.float32), np.zeros((nl, ns), np.float32),
            np.zeros((nl, ns), np.int32), np.zeros((nl, ns), np.float32),
            np.zeros((nl, ns), np.int32), np.zeros((nl, ns), np.int32),
            np.zeros((nl, ns), np.float32)]
    call(zs, *args, *outs)                                      # the right arrays run
    with pytest.raises(TypeError, match="exposure 1"):
        call((zs[0], zs[1][:, :, ::-1], zs[2]), *args, *outs)  # not C-contiguous
    with pytest.raises(TypeError, match="output 2"):
        call(zs, *args, *outs[:2], outs[2].astype(np.int64), *outs[3:])
    with pytest.raises(TypeError, match="3 exposures"):
        call(zs[:2], *args, *outs)
    with pytest.raises(TypeError, match="exposure 0 must be a C-contiguous uint16"):
        call(tuple(z.astype(np.int16) for z in zs), *args, *outs)   # another raw type
    ro = [o.copy() for o in outs]
    ro[3].flags.writeable = False            # it would write through a read-only view
    with pytest.raises(TypeError, match="output 3 must be writeable"):
        call(zs, *args, *ro)
    zs_ro = tuple(z.copy() for z in zs)
    for z in zs_ro:
        z.flags.writeable = False            # raw data of a read-only memory map: read only
    call(zs_ro, *args, *outs)


def test_every_array_a_kernel_writes_is_one_of_its_parameters():
    from mehs.synthesis._native_specs import KERNELS

    for kind, spec in KERNELS.items():
        names = {name for name, t in spec.params if ":" in t}
        assert spec.writes and set(spec.writes) <= names, kind


def test_unsupported_raw_types_and_no_cache_use_numba(cache, monkeypatch):
    from mehs.synthesis import _native

    stack, t, darks = _bracket(3, np.int64)
    r = merge_bracket(stack, t, darks=darks)
    assert not cache.exists() or not list(cache.glob("*int64*"))
    monkeypatch.setenv("MEHS_CACHE_DIR", "")
    assert not _native.supported("poisson_linear", np.uint16, 3)
    monkeypatch.setenv("MEHS_CACHE_DIR", str(cache.parent))
    assert _native.supported("poisson_linear", np.uint16, 3)
    swapped = np.dtype(np.uint16).newbyteorder()              # an ENVI file of the other order
    assert not _native.supported("poisson_linear", swapped, 3)
    assert_same_merge_bits(r, merge_bracket([s.astype(np.int64) for s in stack], t, darks=darks))


def test_numba_still_works_after_a_stored_kernel_bound_its_error_paths(cache, tmp_path):
    """Loading a stored kernel in a process without numba binds numba's error helpers to
    ``abort``; numba started later in that process must still allocate and raise."""
    stack, t, darks = _bracket(3)
    merge_bracket(stack, t, darks=darks)                        # stored
    np.save(tmp_path / "stack.npy", np.stack(stack))
    code = (
        "import sys, numpy as np\n"
        "from mehs.synthesis.merge import merge_bracket\n"
        f"s = np.load({str(tmp_path / 'stack.npy')!r})\n"
        f"merge_bracket(list(s), {t!r})\n"
        "assert 'numba' not in sys.modules\n"
        "from numba import njit\n"
        "@njit\n"
        "def f(n):\n"
        "    a = np.arange(n)\n"
        "    if n > 5:\n"
        "        raise ValueError('too big')\n"
        "    return a.sum()\n"
        "assert f(4) == 6\n"
        "try:\n"
        "    f(9)\n"
        "except ValueError as e:\n"
        "    print('RAISED', e)\n")
    env = dict(os.environ, MEHS_CACHE_DIR=str(cache.parent), PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "RAISED too big" in r.stdout


@pytest.mark.parametrize("stored", [True, False])
def test_a_bracket_of_the_other_byte_order_merges_like_the_native_one(cache, monkeypatch,
                                                                       stored):
    """An ENVI file written big-endian is memory-mapped with a swapped dtype: swapped chunk
    by chunk, it gives the native bracket's numbers (it crashed numba's typing before)."""
    stack, t, darks = _bracket(3)
    ref = merge_bracket(stack, t, darks=darks)
    if not stored:
        monkeypatch.setenv("MEHS_CACHE_DIR", "")
    swapped = [s.astype(s.dtype.newbyteorder()) for s in stack]
    assert not swapped[0].dtype.isnative and np.array_equal(swapped[0], stack[0])
    assert_same_merge_bits(ref, merge_bracket(swapped, t, darks=darks))


def test_a_cache_that_cannot_take_entries_compiles_nothing_extra(tmp_path, monkeypatch):
    """Where the cache folder cannot be written, every process would pay for a compile it
    cannot keep: the entry point is not compiled and numba's kernel runs."""
    from mehs.synthesis import _native

    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv("MEHS_CACHE_DIR", str(blocker))
    monkeypatch.setattr(_native, "_loaded", {})
    compiled = []
    monkeypatch.setattr(_native, "_compile", lambda *a: compiled.append(a))
    stack, t, darks = _bracket(3)
    r = merge_bracket(stack, t, darks=darks)
    assert compiled == [] and blocker.is_file()
    monkeypatch.setenv("MEHS_CACHE_DIR", "")
    assert_same_merge_bits(r, merge_bracket(stack, t, darks=darks))


def test_an_entry_point_compiled_in_a_child_process_is_loaded(cache, monkeypatch):
    """A first-ever fuse compiles the photon-transfer passes in a child process while it
    compiles the merge kernel; the parent then loads the child's entry."""
    from mehs.synthesis import _native

    _reset(monkeypatch)
    assert _native.build_in_background("ptc_pass", np.float32)
    assert not _native.build_in_background("ptc_pass", np.float32)     # one child
    fn = _native.native_kernel("ptc_pass", np.float32, build=False)    # waits for it
    assert fn is not None
    assert len(list(cache.glob("ptc_pass-float32-*.o"))) == 1
    _reset(monkeypatch)
    assert not _native.build_in_background("ptc_pass", np.float32)     # already stored
    monkeypatch.setenv("MEHS_CACHE_DIR", "")
    assert not _native.build_in_background("ptc_pass", np.float32)     # no cache: none


def test_a_child_compiling_elsewhere_is_neither_duplicated_nor_awaited(cache, monkeypatch):
    """Another process's child holds the entry's ``.building`` lock: this process starts
    no second child and :func:`building` says so (its caller then uses numpy's passes
    instead of waiting); once the lock is gone, it builds as usual."""
    import fcntl

    from mehs.synthesis import _native

    _reset(monkeypatch)
    _, stem = _native._key("ptc_pass", np.dtype(np.float32), 0)
    cache.mkdir(parents=True, exist_ok=True)
    fd = os.open(cache / f"{stem}.building", os.O_CREAT | os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)                 # "another process's child"
    try:
        assert _native.building("ptc_pass", np.float32)
        assert not _native.build_in_background("ptc_pass", np.float32)
    finally:
        os.close(fd)
    assert not _native.building("ptc_pass", np.float32)
    assert _native.build_in_background("ptc_pass", np.float32)   # now this one builds
    assert _native.building("ptc_pass", np.float32)              # its own child
    assert _native.native_kernel("ptc_pass", np.float32, build=False) is not None
    assert not _native.building("ptc_pass", np.float32)          # stored


@pytest.mark.parametrize("weighted", [False, True])
def test_the_binned_entry_points_shape_check_finds_each_argument_in_both_layouts(weighted):
    """The binned kernels index without bounds checks: their stored entry points' check
    must refuse every mis-shaped argument, in the Poisson layout and in the weighted one
    (``L`` and ``floor`` after the times). Review, session 35: no test refused one."""
    from mehs.synthesis._native_specs import _check_merge_binned

    P, nl, nb, ns = 3, 2, 6, 17
    f4 = np.float32
    head = [tuple(np.zeros((nl, nb, ns), np.uint16) for _ in range(P)),
            np.zeros((P, nb, ns), f4), np.full(nb, 4000, f4), np.ones(P, f4)]
    mid = [1.0, np.ones(P, f4), 0.0, np.ones(nb, f4), True, True, 4,
           tuple(np.zeros(ns, f4) for _ in range(P)), np.zeros(ns, f4), np.zeros(ns, np.int32)]
    outs = [np.zeros((nl, nb, ns), f4)] + [np.zeros((nl, ns), f4) for _ in range(6)]
    extra = [4096, f4(0.5)] if weighted else []
    at = len(head) + len(extra)            # where `mid` starts

    def args(**change):
        a = head + extra + mid + outs
        for k, v in change.items():
            a[{"avar": at + 1, "cal": at + 3, "nbin": at + 6, "ysum": at + 7, "xps": at + 8,
               "bms": at + 9}[k]] = v
        return a

    _check_merge_binned(P, args())                                     # the right arrays
    for k, v, says in (("avar", np.ones(P + 1, f4), "avar"), ("cal", np.ones(nb - 1, f4), "cal"),
                       ("nbin", 0, "nbin"), ("ysum", tuple(np.zeros(ns - 1, f4) for _ in range(P)),
                                             "scratch"),
                       ("xps", np.zeros(ns + 1, f4), "scratch"),
                       ("bms", np.zeros(2, np.int32), "scratch")):
        with pytest.raises(TypeError, match=says):
            _check_merge_binned(P, args(**{k: v}))
