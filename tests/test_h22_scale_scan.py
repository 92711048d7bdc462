"""Line-scan cameras' sizes and band sets (FX10 / FX17 / binned / Pika-like) through fuse and
resample: memory of the streaming paths, band-set errors, odd sizes (task h22 C).

Brackets are written in the Specim ENVI layout by ``benchmarks/bench_large_scan.py``
(uint16 BIL, 12-bit, ``tint``, per-exposure darks) at small sizes.
"""

from __future__ import annotations

import sys
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_large_scan import write_envi_u16, write_scan_bracket  # noqa: E402

from mehs.cli import main as mehs_main  # noqa: E402
from mehs.io.envi import read_envi  # noqa: E402
from mehs.synthesis.bracket import load_bracket  # noqa: E402
from mehs.synthesis.merge import NoiseModel, merge_bracket  # noqa: E402


def _fuse(folders, **kw):
    from mehs.synthesis.fuse import fuse_bracket

    kw = {"response": "linear", "noise": NoiseModel(0.5, 3.0, 0.0, 1.0), "ghosts": "off",
          "saturation": 4000.0, **kw}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fuse_bracket(load_bracket(folders), **kw)


def _raw(folder: Path, k: int, lines: int, samples: int, bands: int) -> np.ndarray:
    """The raw cube read independently of mehs: BIL uint16 → (lines, samples, bands)."""
    a = np.fromfile(folder / "capture" / f"scan{k}.raw", dtype="<u2")
    return a.reshape(lines, bands, samples).transpose(0, 2, 1)


# ------------------------------------------------------------------ memory

def test_descending_wavelengths_are_a_view_not_a_copy_of_the_cube(tmp_path):
    """A descending band order (common in spectrometer files) was sorted by copying the
    whole cube into memory: every exposure of a bracket read whole (a 5000-line FX10
    exposure is 2.3 GB). Reversed, it is a view of the memory map: the cube read holds
    what the ascending one holds (its header's lists), not its data."""
    wl = np.linspace(1000.0, 400.0, 56)
    shape = (96, 64, 56)
    (fd,) = write_scan_bracket(tmp_path / "d", *shape[:2], wavelengths=wl, times_ms=(2.0,))
    (fa,) = write_scan_bracket(tmp_path / "a", *shape[:2], wavelengths=wl[::-1], times_ms=(2.0,))
    nbytes = int(np.prod(shape)) * 2
    held = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        read_envi(fa / "capture" / "DARKREF_scan0.hdr")      # imports and caches warmed
        for name, f in (("asc", fa), ("desc", fd)):
            tracemalloc.start()
            try:
                cube = read_envi(f / "capture" / "scan0.hdr")
                held[name] = tracemalloc.get_traced_memory()[0]   # while the cube lives
            finally:
                tracemalloc.stop()
    extra = held["desc"] - held["asc"]
    assert extra < 0.25 * nbytes, f"the descending cube held {extra / nbytes:.2f}× the cube more"
    assert np.all(np.diff(cube.wavelengths) > 0)
    truth = _raw(fd, 0, *shape)[:, :, ::-1]
    np.testing.assert_array_equal(np.asarray(cube.data), truth)
    np.testing.assert_allclose(cube.wavelengths, wl[::-1])


def test_merge_copies_of_a_non_bil_stack_are_bounded_by_bytes(monkeypatch):
    """A stack the kernel cannot read in place (BIP, reversed bands, another byte order)
    was copied chunk_lines=128 lines at a time: 176 MB a chunk of an FX10, per thread.
    The copies are now bounded by COPY_CHUNK_BYTES; the result is unchanged."""
    import mehs.synthesis._ranges as ranges
    import mehs.synthesis.merge as merge

    monkeypatch.setattr(ranges, "thread_count", lambda: 1)
    rng = np.random.default_rng(5)
    nl, ns, nb = 64, 48, 40
    x = rng.uniform(5, 400, (nl, ns, nb)).astype(np.float32)
    t = [1.0, 4.0, 16.0]
    stack = [np.clip(np.rint(x * tj + rng.normal(0, 2, x.shape) + 60), 0, 4095).astype(np.uint16)
             for tj in t]                                       # BIP: (l, s, b) C order
    darks = [np.full((ns, nb), 60.0, np.float32)] * 3
    kw = dict(darks=darks, noise=NoiseModel(1.0, 2.0, 0.0), saturation=4000.0)
    ref = merge_bracket([np.ascontiguousarray(s.transpose(0, 2, 1)).transpose(0, 2, 1)
                         for s in stack], t, **kw).radiance     # BIL views: read in place
    monkeypatch.setattr(merge, "COPY_CHUNK_BYTES", 8 * ns * nb * 2 * 3, raising=False)  # 8 lines
    tracemalloc.start()
    try:
        res = merge_bracket(stack, t, **kw)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    out_bytes = nl * ns * nb * 4
    stack_bytes = 3 * nl * ns * nb * 2
    # the output, per-pixel planes and one 8-line copy; the whole stack copied was 2.2×
    assert peak < out_bytes + 0.5 * stack_bytes, (peak, out_bytes, stack_bytes)
    np.testing.assert_array_equal(res.radiance, ref)


# ------------------------------------------------------------------ band sets

def test_fx17_cube_fuses_and_resample_to_visible_is_refused_naming_the_file(tmp_path, capsys):
    """An FX17 (900–1700 nm) has no visible band: fuse works, resample to 400–700 nm is
    refused with one clear sentence naming the file."""
    folders = write_scan_bracket(tmp_path / "fx17", 24, 40, 112, (900.0, 1700.0))
    out = tmp_path / "fused"
    assert mehs_main(["fuse", *map(str, folders), "--out", str(out)]) == 0
    cube = read_envi(out / "radiance.hdr")
    assert cube.shape == (24, 40, 112) and 899 < cube.wavelengths[0] < cube.wavelengths[-1] < 1701
    capsys.readouterr()
    assert mehs_main(["resample", str(out / "radiance.hdr"), str(tmp_path / "hs31.hdr")]) != 0
    err = capsys.readouterr().err
    assert "no source band covers 400–700 nm" in err, err
    assert str(out / "radiance.hdr") in err and "900..1700 nm" in err, err
    assert not (tmp_path / "hs31.hdr").exists()


def test_binned_56_band_resample_matches_spy_band_resampler(tmp_path):
    """A 56-band binned FX10 (400–1000 nm) resampled to 31 bands: SPy's BandResampler with
    the same centres and FWHMs is the independent truth."""
    spectral = pytest.importorskip("spectral")
    from mehs.synthesis.resample import resample_cube

    folders = write_scan_bracket(tmp_path / "b56", 20, 24, 56)
    cube = _fuse(folders).radiance
    res = resample_cube(cube, np.arange(400.0, 701.0, 10.0), fwhm=10.0)
    spy = spectral.BandResampler(cube.wavelengths, np.arange(400.0, 701.0, 10.0),
                                 cube.fwhm, np.full(31, 10.0))
    x = np.asarray(cube.data, dtype=np.float64).reshape(-1, 56)
    truth = np.array([spy(p) for p in x]).reshape(20, 24, 31)
    np.testing.assert_allclose(res.data, truth, rtol=2e-5, atol=1e-5 * np.abs(truth).max())


def test_micrometre_and_descending_brackets_fuse_as_the_nanometre_one(tmp_path):
    """The same raw data with wavelengths in µm, or bands in descending order, fuse to the
    same radiance per wavelength as the nm, ascending bracket."""
    nl, ns, nb = 20, 24, 56
    wl = np.linspace(400.0, 1000.0, nb)
    asc = write_scan_bracket(tmp_path / "nm", nl, ns, nb, seed=7)
    um = write_scan_bracket(tmp_path / "um", nl, ns, nb, seed=7, units="Micrometers")
    desc = []
    fw = np.full(nb, 1.5 * (wl[1] - wl[0]))
    for k, (f, t) in enumerate(zip(asc, (1.0, 8.0, 64.0))):      # bands reversed on disk
        d = tmp_path / "desc" / f.name
        for name, n in ((f"scan{k}", nl), (f"DARKREF_scan{k}", 8)):
            a = np.fromfile(f / "capture" / f"{name}.raw", "<u2").reshape(n, nb, ns)
            write_envi_u16(d / "capture" / f"{name}.hdr", [a.transpose(0, 2, 1)[:, :, ::-1]],
                           lines=n, samples=ns, bands=nb, wavelengths=wl[::-1], fwhm=fw,
                           tint_ms=t)
        desc.append(d)
    ref = _fuse(asc)
    for folders in (um, desc):
        r = _fuse(folders)
        np.testing.assert_allclose(r.radiance.wavelengths, wl, atol=1e-3)
        np.testing.assert_allclose(r.radiance.fwhm, fw, atol=1e-3)
        np.testing.assert_array_equal(np.asarray(r.radiance.data), np.asarray(ref.radiance.data))


# ------------------------------------------------------------------ odd sizes

def test_odd_sizes_fuse_whole_equals_halves_and_chunking(tmp_path):
    """130 lines (not a multiple of the 128-line chunk) × 37 samples (no vector width):
    the bracket fused whole equals its two halves fused apart and concatenated, and a
    7-line chunking."""
    nl, ns, nb = 130, 37, 56
    folders = write_scan_bracket(tmp_path / "odd", nl, ns, nb, seed=3, chunk=9)
    whole = _fuse(folders)
    np.testing.assert_array_equal(np.asarray(_fuse(folders, chunk_lines=7).radiance.data),
                                  np.asarray(whole.radiance.data))
    b = load_bracket(folders)
    parts = []
    for sl in (slice(0, 61), slice(61, nl)):
        r = merge_bracket([e.data[sl] for e in b.exposures], b.times_ms, darks=b.darks,
                          noise=NoiseModel(0.5, 3.0, 0.0, 1.0), saturation=4000.0,
                          clip_negative=False)
        parts.append(r.radiance)
    np.testing.assert_array_equal(np.concatenate(parts), np.asarray(whole.radiance.data))
    # the Poisson estimator by hand where every exposure is usable (independent of the kernel)
    raws = [_raw(f, k, nl, ns, nb).astype(np.float64) - b.darks[k] for k, f in enumerate(folders)]
    usable = np.all([_raw(f, k, nl, ns, nb) < 4000 for k, f in enumerate(folders)], axis=0)
    est = sum(raws) / sum(b.times_ms)
    np.testing.assert_allclose(np.asarray(whole.radiance.data)[usable], est[usable], rtol=1e-5,
                               atol=1e-4)


@pytest.mark.parametrize("lines, samples", [(1, 1), (1, 37), (37, 1)])
def test_one_line_or_one_sample_scans_fuse_and_resample(tmp_path, lines, samples):
    folders = write_scan_bracket(tmp_path / "s", lines, samples, 56, seed=2)
    out = tmp_path / "f"
    assert mehs_main(["fuse", *map(str, folders), "--out", str(out)]) == 0
    assert mehs_main(["resample", str(out / "radiance.hdr"), str(tmp_path / "hs.hdr")]) == 0
    hs = read_envi(tmp_path / "hs.hdr")
    assert hs.shape == (lines, samples, 31) and np.all(np.isfinite(hs.data))
