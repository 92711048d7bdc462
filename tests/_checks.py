"""Checks shared by several test files (imported as ``_checks``, like ``_simdevice``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: numba told to build without vectors: nothing to look for in the kernels' code
NO_VECTOR_BUILD = any((os.environ.get("NUMBA_CPU_NAME", "").lower() == "generic",
                       os.environ.get("NUMBA_OPT", "").strip() == "0",
                       os.environ.get("NUMBA_BOUNDSCHECK", "").strip() not in ("", "0")))


def one_pass_division_counts(entry, *, weighted: bool, binned: bool) -> tuple[int, int, str]:
    """``(vector, scalar, ir)``: the ``fdiv`` of a one-pass merge kernel compiled afresh by
    numba (numba shows no code of a cached kernel) for 2 × 3 × 16 samples of
    :data:`DEFAULT_TUNED_EXPOSURES` exposures, in vector and in scalar form, and its IR.
    A vectorised kernel keeps one scalar division per vector one for the loop's remainder."""
    import re

    import numba

    from mehs.synthesis._native_child import DEFAULT_TUNED_EXPOSURES

    kernel = numba.njit(nogil=True, error_model="numpy")(entry.py_func)
    P, nl, nb, ns = DEFAULT_TUNED_EXPOSURES, 2, 3, 16
    f4 = np.float32
    zs = tuple(np.full((nl, nb, ns), 100 * (j + 1), np.uint16) for j in range(P))
    outs = (np.zeros((nl, nb, ns), f4), np.zeros((nl, ns), f4), np.zeros((nl, ns), np.int32),
            np.zeros((nl, ns), f4), np.zeros((nl, ns), np.int32), np.zeros((nl, ns), np.int32),
            np.zeros((nl, ns), f4))
    scratch = ((2, tuple(np.zeros(ns, f4) for _ in range(P)), np.zeros(ns, f4),
                np.zeros(ns, np.int32)) if binned else ())
    head = (zs, np.zeros((P, nb, ns), f4), np.full(nb, 4000, f4),
            (4.0 ** np.arange(P)).astype(f4)) + ((4096, f4(0.5)) if weighted else ())
    kernel(*head, 1.5, np.full(P, 9, f4), 0.0, np.ones(nb, f4), True, True, *scratch, *outs)
    assert outs[0].max() > 0 and outs[2].max() > 0
    (ir,) = kernel.inspect_llvm().values()
    return (len(re.findall(r"fdiv (?:\w+ )*<\d+ x float>", ir)),
            len(re.findall(r"fdiv (?:\w+ )*float", ir)), ir)


#: every output of :func:`mehs.synthesis.merge.merge_bracket` that is an array
MERGE_FIELDS = ("radiance", "confidence", "mask", "chi2", "dof", "mean_radiance")


def assert_same_merge_bits(got, ref) -> None:
    """Two merge results hold the same dtypes and the same bytes in every output array."""
    for k in MERGE_FIELDS:
        a = np.ascontiguousarray(getattr(got, k))
        b = np.ascontiguousarray(getattr(ref, k))
        assert a.dtype == b.dtype, k
        np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8), err_msg=k)


#: Python source that defines ``libc`` and ``M`` (glibc's ``struct mallinfo2``) so that
#: ``libc.mallinfo2()`` tells how much of the heap (``arena``) and of separate
#: mappings (``hblkhd``) the process holds; for tests run in a fresh interpreter.
MALLINFO2 = (
    "import ctypes\n"
    "libc = ctypes.CDLL('libc.so.6')\n"
    "class M(ctypes.Structure):\n"
    "    _fields_ = [(n, ctypes.c_size_t) for n in ('arena', 'ordblks', 'smblks', 'hblks',\n"
    "               'hblkhd', 'usmblks', 'fsmblks', 'uordblks', 'fordblks', 'keepcost')]\n"
    "libc.mallinfo2.restype = M\n")


def has_mallinfo2() -> bool:
    """glibc ≥ 2.33."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return False
    return True


def contrast_rgb(h: int, w: int, seed: int = 3) -> np.ndarray:
    """float32 ``(h, w, 3)`` with strong left-right and top-bottom contrast: a tile's own
    global-pooling means differ much from the whole image's (tiling tests)."""
    rng = np.random.default_rng(seed)
    x = rng.gamma(1.0, 1.0, (h, w, 3)).astype(np.float32)
    x[:, : w // 3] *= 4.0
    x[: h // 2, :, 1] *= 0.2
    return x


def write_mat73(path: Path, variables: dict) -> Path:
    """A MATLAB v7.3 MAT-file: HDF5 behind a 512-byte userblock with MATLAB's 128-byte header;
    arrays stored column-major (axes reversed), each with its MATLAB_class attribute."""
    import h5py

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w", userblock_size=512) as f:
        for k, v in variables.items():
            v = np.asarray(v)
            d = f.create_dataset(k, data=v.T)
            d.attrs["MATLAB_class"] = np.bytes_("single" if v.dtype == np.float32 else "double")
    text = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Tue Dec  1 12:00:00 2026 HDF5 schema 1.00 ."
    header = text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM"
    with open(path, "r+b") as fh:
        fh.write(header)
    return path


def colorchecker_pair(h: int, w: int, seed: int, block: int = 8):
    """A :class:`mehs.ssr.net.train.TrainingPair` ``(h, w)``: blocks of ColorChecker
    reflectances (colour-science) under D65 at brightnesses 0.5–20× (a 40× range), id
    ``s<seed>`` (torch needed)."""
    import colour

    from mehs.rgb import WAVELENGTHS_31, spectra_to_linear_sRGB
    from mehs.ssr.net.train import TrainingPair

    shape = colour.SpectralShape(400, 700, 10)
    refl = np.array([sd.copy().align(shape).values
                     for sd in colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values()])
    ill = colour.SDS_ILLUMINANTS["D65"].copy().align(shape).values / 100
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, 24, size=(-(-h // block), -(-w // block)))
    gain = rng.uniform(0.5, 20, size=idx.shape + (1,))
    up = lambda a: a.repeat(block, 0).repeat(block, 1)[:h, :w]  # noqa: E731
    hs = (up(refl[idx]) * ill * up(gain)).astype(np.float32)
    return TrainingPair(spectra_to_linear_sRGB(hs, WAVELENGTHS_31), hs, id=f"s{seed}")


def _fuse_quiet(br, curve):
    """``br`` fused with ``curve``, no ghost detection, its warnings (a curve under test may
    be poor) silenced: the merge the response measures below compare."""
    import warnings

    from mehs.synthesis.fuse import fuse_bracket

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fuse_bracket(br, response=curve, ghosts="off")


def decile_bias(br, sim, curve) -> np.ndarray:
    """Radiance bias per brightness decile of the simulator's truth, one global scale
    removed: ``(10,)`` of ``median(fused / truth) / overall median − 1`` when ``br`` (the
    bracket of ``sim``) is fused with ``curve``. The response tests' measure of a curve."""
    res = _fuse_quiet(br, curve)
    rad = np.asarray(res.radiance.data, np.float64)
    truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms
    ok = np.broadcast_to((res.mask == 0)[..., None] & (truth > 0), rad.shape)
    lr = np.log(np.maximum(rad[ok], 1e-12) / truth[ok])
    tv = truth[ok]
    qs = np.quantile(tv, np.linspace(0, 1, 11))
    return np.array([np.expm1(np.median(lr[(tv >= a) & (tv < b)]) - np.median(lr))
                     for a, b in zip(qs[:-1], qs[1:])])


def bracket_of(sim, wl):
    """The :class:`~mehs.synthesis.bracket.Bracket` of a simulated bracket ``sim`` (12-bit,
    its darks, no white references), bands ``wl``."""
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket

    n = len(sim.exposures)
    return Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                   [None] * n, sim.times_ms, wl, bit_depth=12)


def true_curve(sensor):
    """The simulated ``sensor``'s own inverse response as a raw-level 12-bit curve: merging
    with it is the floor of the response tests' measures."""
    from mehs.synthesis.response import ResponseCurve

    z = np.arange(4096)
    return ResponseCurve(np.log(np.maximum(sensor.inverse_response_dn(z), 1e-3)), 12,
                         parameters={"levels": "raw"})


def signal_decile_excess(sim, br, sensor, curve, min_dn: float = 20.0) -> np.ndarray:
    """``(10,)``: per brightness decile of the simulator's truth, the mean radiance merged
    with ``curve`` minus that merged with the sensor's true curve, relative to the decile's
    true radiance (each merge scaled to the truth's total). Only samples whose true signal
    in the longest exposure is ``≥ min_dn`` DN count: on a dark bracket most samples are
    read noise, whose deciles say nothing about a curve (the true curve's own merge is off
    there by thousands of per cent)."""
    def fused(c):
        res = _fuse_quiet(br, c)
        return np.asarray(res.radiance.data, np.float64), res.mask == 0

    truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms
    (ra, oka), (rb, okb) = fused(true_curve(sensor)), fused(curve)
    ok = (np.broadcast_to((oka & okb)[..., None], truth.shape)
          & (truth * float(np.max(br.times_ms)) >= min_dn))
    t, a, b = truth[ok], ra[ok], rb[ok]
    a, b = a * t.sum() / a.sum(), b * t.sum() / b.sum()
    qs = np.quantile(t, np.linspace(0, 1, 11))
    return np.array([(b[m].sum() - a[m].sum()) / t[m].sum()
                     for m in ((t >= lo) & (t <= hi) for lo, hi in zip(qs[:-1], qs[1:]))])


def log_ratio_to_true_curve(br, sim, sensor, curve, min_dn: float = 20.0):
    """``(q, tv)``: per sample, ``ln`` of ``curve``'s merge over the merge of the same bracket
    with the sensor's true curve (same noise, so the ratio is the curve's own error), and
    the sample's true radiance; over samples unmasked in both merges, positive in both, with
    ``≥ min_dn`` DN of true signal in the longest exposure."""
    import warnings

    from mehs.synthesis.fuse import fuse_bracket

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got, ref = (fuse_bracket(br, response=c, ghosts="off", check_response=False)
                    for c in (curve, true_curve(sensor)))
    rad, rr = (np.asarray(r.radiance.data, np.float64) for r in (got, ref))
    truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms
    ok = (((got.mask == 0) & (ref.mask == 0))[..., None] & (rad > 0) & (rr > 0)
          & (truth * float(sim.times_ms.max()) >= min_dn))
    return np.log(rad[ok] / rr[ok]), truth[ok]


def decile_medians(q, tv) -> np.ndarray:
    """``(10,)``: the median of ``q`` in each decile of ``tv`` (both ends included)."""
    qs = np.quantile(tv, np.linspace(0, 1, 11))
    return np.array([np.median(q[(tv >= a) & (tv <= b)]) for a, b in zip(qs[:-1], qs[1:])])


#: the dataset's 31 bands (400-700 nm, 10 nm)
_WL31 = np.arange(400.0, 701.0, 10.0)


def ohta_chart(level, lines=12, samples=18):
    """ColorChecker N Ohta reflectances × D65 (colour-science's measured spectra) on the
    31 bands, brightness rising left to right, a 100× lamp block: times ``level``."""
    import colour

    cc = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    refl = np.array([[sd[w] for w in _WL31] for sd in cc.values()])
    ill = np.array([d65[w] for w in _WL31]) / 100.0
    r = (np.arange(lines) * 4 // lines)[:, None]
    c = (np.arange(samples) * 6 // samples)[None, :]
    cube = refl[r * 6 + c] * ill * np.linspace(0.2, 2.0, samples)[None, :, None]
    cube[:2, :3] *= 100.0
    return (cube * level).astype(np.float32)


def colour_srgb(cube):
    """Pseudo-HDR-RGB the outside way: colour.msds_to_XYZ (integration, flat illuminant,
    k = 100/Σȳ) then the IEC 61966-2-1 matrix, negatives clipped (float64)."""
    import colour

    shape = colour.SpectralShape(400, 700, 10)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    xyz = colour.msds_to_XYZ(cube.astype(np.float64), cmfs=cmfs, method="Integration",
                             shape=shape) / 100.0
    from mehs.rgb import XYZ_TO_SRGB

    return np.maximum(xyz @ XYZ_TO_SRGB.T, 0.0)


def peak_live_bytes(fn) -> int:
    """Peak bytes of live torch tensor storages while ``fn()`` runs, its result dropped
    (counted here, independently of mehs's own memory probe)."""
    import weakref

    import torch  # noqa: F401
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils._pytree import tree_leaves

    class Count(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.live = self.peak = 0
            self.seen = set()

        def _gone(self, key, n):
            self.live -= n
            self.seen.discard(key)

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            for t in tree_leaves(out):
                if isinstance(t, torch.Tensor):
                    s = t.untyped_storage()
                    if id(s) not in self.seen:
                        self.seen.add(id(s))
                        self.live += s.nbytes()
                        weakref.finalize(s, self._gone, id(s), s.nbytes())
            self.peak = max(self.peak, self.live)
            return out

    with Count() as c:
        y = fn()
        del y
    return c.peak
