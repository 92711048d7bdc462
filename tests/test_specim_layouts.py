"""Specim IQ folders in the public layout, loaded as brackets: times, references, orientation.

The folders are written byte for byte here (ENVI header text of a real IQ
capture, uint16 BIL data), not by mehs, so the reader is checked against the
layout itself and against SPy reading the same files.
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.errors import FormatError

# Band centres of the Specim IQ (fligt/iqcampy demo capture; the same list as
# tests/test_io_real_formats.py): 204 values, 397.32 … 1003.58 nm, uneven steps.
from test_io_real_formats import IQ_WAVELENGTHS  # tests/ is on sys.path under pytest

S, B = 3, 204  # samples, bands


def iq_header(lines: int, tint: float, samples: int = S) -> str:
    """A Specim IQ capture header (as printed in iqcampy's notebook), cut to ``samples``."""
    wl = ",\n".join(f"{w:.2f}" for w in IQ_WAVELENGTHS)
    return (f"ENVI\ndescription = {{Data recorded with Specim IQ}}\nsamples = {samples}\n"
            f"lines = {lines}\nbands = {B}\nheader offset = 0\nfile type = ENVI\n"
            "data type = 12\ninterleave = BIL\nsensor type = SPECIM IQ\nbyte order = 0\n"
            "default bands = {70,53,19}\nacquisition date = 03-02-2021\nerrors = none\n"
            f"binning = {{1,1}}\ntint = {tint:g}\nfps = 10\nwavelength = {{\n{wl}\n}}\n")


def put(folder, stem, cube_lsb, tint):
    """``cube_lsb`` (lines, samples, bands) → ``capture/<stem>.hdr|.raw`` (BIL, little-endian)."""
    cap = folder / "capture"
    cap.mkdir(parents=True, exist_ok=True)
    (cap / f"{stem}.hdr").write_text(iq_header(cube_lsb.shape[0], tint, cube_lsb.shape[1]))
    (cap / f"{stem}.raw").write_bytes(
        np.ascontiguousarray(cube_lsb.transpose(0, 2, 1)).astype("<u2").tobytes())


def line(value):
    return np.full((1, S, B), value, np.uint16)


def iq_folder(root, cid, t, *, white=None, white_t=None, white_dark=None, dark_t=None,
              lines=2):
    """A capture at ``t`` ms whose dark is ``100 + 2·t`` DN; optional (pre-set) white."""
    f = root / cid
    put(f, cid, np.full((lines, S, B), 1000, np.uint16), t)
    put(f, f"DARKREF_{cid}", line(100 + 2 * t), t if dark_t is None else dark_t)
    if white is not None:
        put(f, f"WHITEREF_{cid}", line(white), t if white_t is None else white_t)
    if white_dark is not None:
        put(f, f"WHITEDARKREF_{cid}", line(white_dark), t if white_t is None else white_t)
    return f


def test_preset_white_uses_its_own_dark_and_integration_time(tmp_path):
    # Specim IQ "pre-set white reference": WHITEREF recorded earlier at its own
    # integration time, with its own dark in WHITEDARKREF. Reflectance is
    # (S - D) / (W - WD) · t_W / t_S (HSItools hsi_normalize: "tint = integration
    # times for white reference and sample data"; Prediktera Breeze: the white's
    # "stored dark reference"). The white's signal is 30 DN/ms, recorded at
    # 20 ms over a dark of 140 DN; the captures are at 10 and 40 ms.
    from mehs.synthesis.bracket import load_bracket

    paths = [iq_folder(tmp_path, f"c{t}", t, white=140 + 30 * 20, white_t=20, white_dark=140)
             for t in (10, 40)]
    b = load_bracket(paths)
    for w, d, t in zip(b.white, b.darks, b.times_ms):
        # consumers (calibration from the white line) take (white - dark) / t per exposure;
        # before the fix this was 62 and 14 DN/ms
        np.testing.assert_allclose((w - d) / t, 30.0, rtol=1e-6)


def test_white_at_another_time_without_its_own_dark(tmp_path):
    # no WHITEDARKREF: the capture's dark serves both, the time ratio still applies
    from mehs.synthesis.bracket import load_bracket

    paths = [iq_folder(tmp_path, f"c{t}", t, white=(100 + 2 * t) + 30 * 20, white_t=20)
             for t in (10, 40)]
    b = load_bracket(paths)
    for w, d, t in zip(b.white, b.darks, b.times_ms):
        np.testing.assert_allclose((w - d) / t, 30.0, rtol=1e-6)


def test_white_at_the_capture_time_is_passed_through(tmp_path):
    # the usual in-scene white: same time, the capture's dark — unchanged bits
    from mehs.synthesis.bracket import load_bracket

    paths = [iq_folder(tmp_path, f"c{t}", t, white=3000) for t in (10, 40)]
    b = load_bracket(paths)
    assert all(np.array_equal(w, np.full((S, B), 3000, np.float32)) for w in b.white)


def test_saturated_preset_white_stays_saturated(tmp_path):
    # a white clipped at 4095 says nothing about its signal: scaled down to a
    # shorter time it must not look like a valid (unsaturated) measurement
    from mehs.synthesis.bracket import load_bracket

    paths = [iq_folder(tmp_path, f"c{t}", t, white=4095, white_t=40, white_dark=180)
             for t in (10, 40)]
    b = load_bracket(paths)
    assert all(np.all(w == 4095) for w in b.white)


def test_dark_at_another_time_is_refused_naming_the_file(tmp_path):
    # a dark's level grows with time (dark current): subtracting a 40 ms dark
    # from a 10 ms capture would be silently wrong
    from mehs.synthesis.bracket import load_bracket

    paths = [iq_folder(tmp_path, "c10", 10, dark_t=40), iq_folder(tmp_path, "c40", 40)]
    with pytest.raises(FormatError, match=r"DARKREF_c10\.hdr.*40 ms, the capture at 10 ms"):
        load_bracket(paths)


def test_white_dark_at_another_time_than_its_white_is_refused(tmp_path):
    from mehs.synthesis.bracket import load_bracket

    paths = [iq_folder(tmp_path, f"c{t}", t, white=800, white_t=20, white_dark=140)
             for t in (10, 40)]
    hp = paths[0] / "capture" / "WHITEDARKREF_c10.hdr"
    hp.write_text(hp.read_text().replace("tint = 20", "tint = 25"))
    with pytest.raises(FormatError, match=r"WHITEDARKREF_c10\.hdr.*25 ms, the white"):
        load_bracket(paths)


def test_real_layout_reads_like_spy(tmp_path):
    # orientation, data type, byte order, wavelengths and tint (ms) as SPy reads them
    import spectral.io.envi as envi

    from mehs.io import read_specim_folder

    rng = np.random.default_rng(0)
    raw = rng.integers(0, 4096, size=(4, S, B), dtype=np.uint16)   # lines ≠ samples
    f = tmp_path / "iq"
    put(f, "iq", raw, 98)
    put(f, "DARKREF_iq", line(90), 98)
    cap = read_specim_folder(f)
    img = envi.open(str(f / "capture" / "iq.hdr"))
    spy = np.asarray(img.open_memmap())
    assert cap.raw.data.shape == spy.shape == (4, S, B)
    np.testing.assert_array_equal(cap.raw.data, spy)
    np.testing.assert_array_equal(cap.raw.data, raw)
    assert cap.raw.data.dtype == np.uint16
    np.testing.assert_allclose(cap.raw.wavelengths, img.bands.centers)
    assert cap.raw.integration_time_ms == float(img.metadata["tint"]) == 98.0


def test_scene_uses_the_recorded_camera_bit_depth(tmp_path):
    # `mehs capture` records a real camera's depth in device.camera.bit_depth;
    # a dim first exposure of a 16-bit camera (all ≤ 4095) must not make it 12 bits
    # (before the fix: 12, so every DN above 4013 in the longer exposure was "saturated")
    from mehs.capture import scenefolder as sf
    from mehs.synthesis.bracket import load_bracket

    root = tmp_path / "scene"
    wl = np.array([450.0, 550.0, 650.0])
    doc = sf.new_scene_doc("s", wl, device={"camera": {"id": "cam", "samples": 2, "bands": 3,
                                                       "bit_depth": 16}})
    base = np.arange(4 * 2 * 3, dtype=np.float64).reshape(4, 2, 3) * 100 + 100   # ≤ 2400 DN/ms
    for k, t in enumerate((1.0, 16.0)):
        raw = np.rint(base * t).astype(np.uint16)
        doc["exposures"].append(sf.write_exposure(root, k, t, raw, np.zeros((2, 3)), None,
                                                   wavelengths=wl))
    sf.write_scene_json(root, doc)
    assert load_bracket(root).bit_depth == 16
