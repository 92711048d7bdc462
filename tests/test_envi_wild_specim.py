"""Specim IQ capture folders as the camera (or a copy of one) leaves them, read against SPy.

The folders are written here byte by byte in the IQ's layout (design.md §2.1): CR LF
headers with ``file type = ENVI``, uint16 bil raw cubes, one-line references,
``results/REFLECTANCE_<id>`` float32, ``metadata/<id>.xml``.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import spectral.io.envi as spy_envi

from mehs.io.specim import find_captures, is_specim_folder, read_specim_folder

S, L, B = 6, 4, 204
WL = np.linspace(397.32, 1003.58, B)


def _header(lines: int, dtype: int) -> str:
    return ("ENVI\r\ndescription = {\r\nSpecim IQ}\r\n"
            f"samples = {S}\r\nlines = {lines}\r\nbands = {B}\r\nheader offset = 0\r\n"
            f"file type = ENVI\r\ndata type = {dtype}\r\ninterleave = bil\r\n"
            "sensor type = SPECIM IQ\r\nbyte order = 0\r\ndefault bands = {70,53,19}\r\n"
            "acquisition date = DATE(dd-mm-yyyy): 28-06-2018\r\nerrors = {none}\r\n"
            "binning = {1,1}\r\ntint = 10\r\nfps = 100\r\nwavelength = {\r\n"
            + ",\r\n".join(f"{w:.2f}" for w in WL) + "\r\n}\r\n")


def _make(root, cid, *, upper=False, white=True, reflectance=True):
    """Write a capture folder without a manifest; return (raw, reflectance) in file order."""
    hx, rx, dx = (".HDR", ".RAW", ".DAT") if upper else (".hdr", ".raw", ".dat")
    rng = np.random.default_rng(3)
    for sub in ("capture", "metadata", "results"):
        (root / sub).mkdir(parents=True)
    raw = rng.integers(0, 4096, (L, B, S)).astype("<u2")
    (root / "capture" / f"{cid}{hx}").write_text(_header(L, 12), newline="")
    (root / "capture" / f"{cid}{rx}").write_bytes(raw.tobytes())
    refs = ["DARKREF_"] + (["WHITEREF_"] if white else [])
    for prefix in refs:
        (root / "capture" / f"{prefix}{cid}{hx}").write_text(_header(1, 12), newline="")
        (root / "capture" / f"{prefix}{cid}{rx}").write_bytes(raw[:1].tobytes())
    refl = None
    if reflectance:
        refl = rng.random((L, B, S)).astype("<f4")
        (root / "results" / f"REFLECTANCE_{cid}{hx}").write_text(_header(L, 4), newline="")
        (root / "results" / f"REFLECTANCE_{cid}{dx}").write_bytes(refl.tobytes())
    (root / "metadata" / f"{cid}.xml").write_text(
        '<?xml version="1.0"?><properties><header><key field="integration time">10</key>'
        "</header></properties>")
    return raw, refl


@pytest.mark.parametrize("cid", ["444", "scan-2019_05_01"])
def test_upper_case_extensions_without_manifest(tmp_path, cid):
    # copied through FAT media / Windows tools: 444.HDR, 444.RAW, DARKREF_444.HDR …
    root = tmp_path / "copy" / cid
    raw, refl = _make(root, cid, upper=True)
    assert is_specim_folder(root)
    assert find_captures(tmp_path) == [root]
    cap = read_specim_folder(root)
    assert cap.capture_id == cid
    np.testing.assert_array_equal(np.asarray(cap.raw.data), raw.transpose(0, 2, 1))
    assert cap.darkref is not None and cap.whiteref is not None
    np.testing.assert_array_equal(np.asarray(cap.reflectance.data), refl.transpose(0, 2, 1))
    assert cap.metadata == {"integration time": "10"}


def test_non_digit_id_missing_optional_files_and_reflectance_as_spy(tmp_path):
    cid = "2018-06-28_001"
    root = tmp_path / cid
    raw, refl = _make(root, cid, white=False)
    cap = read_specim_folder(root)
    assert cap.whiteref is None and cap.whitedarkref is None and cap.preview is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spy_raw = spy_envi.open(str(root / "capture" / f"{cid}.hdr")).load(dtype=np.float64)
        spy_refl = spy_envi.open(str(root / "results" / f"REFLECTANCE_{cid}.hdr"),
                                 str(root / "results" / f"REFLECTANCE_{cid}.dat")).load()
    np.testing.assert_array_equal(np.asarray(cap.raw.data), np.asarray(spy_raw))
    np.testing.assert_array_equal(np.asarray(cap.reflectance.data), np.asarray(spy_refl))
    assert cap.reflectance.data.dtype == np.float32 and cap.reflectance.units == "reflectance"
    assert cap.raw.integration_time_ms == 10.0
    assert cap.raw.acquisition_date == "2018-06-28"
    assert cap.raw.default_bands == (69, 52, 18)
    np.testing.assert_allclose(cap.raw.wavelengths, np.round(WL, 2))
