"""Per-band ENVI metadata follows its bands (issue 17, defect 9).

An unsorted BIL file (two spectrometers concatenated) flags one band bad; reading sorts the
bands, and the flag, names and gains must move with them — checked against SPy reading
the file mehs writes back. Resampling to 31 bands recomputes ``bbl`` and drops the lists
that describe source bands.
"""

import warnings

import numpy as np
import pytest

from mehs.io.envi import read_envi, write_envi
from mehs.synthesis.resample import resample_cube

BAD_NM = 664.14


def _unsorted_file(tmp_path):
    """A 198-band BIL uint16 file: 500..1000 nm then 400..~680 nm (not sorted)."""
    rng = np.random.default_rng(0)
    wl = np.concatenate([np.linspace(500.0, 1000.0, 110), np.linspace(400.0, 680.0, 88)])
    wl = np.round(wl, 2)
    bad = int(np.argmin(np.abs(wl - BAD_NM)))
    wl[bad] = BAD_NM  # in the second (shorter-wavelength) block, far from its sorted place
    assert bad >= 110
    lines, samples, bands = 3, 4, wl.size
    data = rng.integers(0, 4096, size=(lines, bands, samples), dtype=np.uint16)  # BIL order
    data.astype("<u2").tofile(tmp_path / "cube.bil")
    bbl = ["1"] * bands
    bbl[bad] = "0"
    names = [f"band {i}" for i in range(bands)]
    gains = [f"{1 + i / 1000:.3f}" for i in range(bands)]
    (tmp_path / "cube.hdr").write_text(
        "ENVI\n"
        f"samples = {samples}\nlines = {lines}\nbands = {bands}\nheader offset = 0\n"
        "file type = ENVI Standard\ndata type = 12\ninterleave = bil\nbyte order = 0\n"
        "wavelength units = Nanometers\n"
        f"wavelength = {{{', '.join(f'{w:.2f}' for w in wl)}}}\n"
        f"bbl = {{{', '.join(bbl)}}}\n"
        f"band names = {{{', '.join(names)}}}\n"
        f"data gain values = {{{', '.join(gains)}}}\n")
    return tmp_path / "cube.hdr", wl, bad, names, gains, data


def test_sorting_moves_bbl_names_and_gains_with_their_bands(tmp_path):
    import spectral

    hdr, wl, bad, names, gains, raw = _unsorted_file(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cube = read_envi(hdr)
    i = int(np.argmin(np.abs(cube.wavelengths - BAD_NM)))
    assert cube.wavelengths[i] == pytest.approx(BAD_NM)
    assert cube.metadata["bbl"][i] == "0" and cube.metadata["bbl"].count("0") == 1
    assert cube.metadata["band names"][i] == names[bad]
    assert cube.metadata["data gain values"][i] == gains[bad]
    np.testing.assert_array_equal(cube.data[:, :, i], raw[:, bad, :])
    out = tmp_path / "back.hdr"
    write_envi(out, cube)
    img = spectral.envi.open(str(out))  # an independent reader of what was written
    centers = np.asarray(img.bands.centers, dtype=float)
    flagged = [float(c) for c, b in zip(centers, img.metadata["bbl"]) if float(b) == 0]
    assert flagged == [pytest.approx(BAD_NM)]
    j = int(np.argmin(np.abs(centers - BAD_NM)))
    assert img.metadata["band names"][j] == names[bad]
    np.testing.assert_array_equal(img.open_memmap()[:, :, j], raw[:, bad, :])


def test_resampling_recomputes_bbl_and_drops_source_band_lists(tmp_path):
    hdr, *_ = _unsorted_file(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cube = read_envi(hdr)
    out = resample_cube(cube)
    assert len(out.metadata["bbl"]) == 31
    assert "band names" not in out.metadata and "data gain values" not in out.metadata
    # The 664.14 nm band sits in the 660 and 670 nm windows; it is left out of them
    # (ENVI: bad bands take no part in processing) and its good neighbours make both,
    # so no target is flagged. Flagging rules: tests/test_resample_audit.py.
    assert out.metadata["bbl"] == [1] * 31
    cube.data[:, :, int(np.argmin(np.abs(cube.wavelengths - BAD_NM)))] = 60000
    np.testing.assert_array_equal(resample_cube(cube).data, out.data)
    write_envi(tmp_path / "r.hdr", out)
    back = read_envi(tmp_path / "r.hdr")
    assert [int(b) for b in back.metadata["bbl"]] == [1] * 31


def test_a_bbl_of_the_wrong_length_is_dropped_with_a_warning(tmp_path):
    from mehs.bandmeta import BandMetadataWarning
    from mehs.cube import SpectralCube

    with pytest.warns(BandMetadataWarning, match="'bbl' has 2 values for 3 bands"):
        cube = SpectralCube(np.zeros((1, 1, 3), np.float32), [400.0, 500.0, 600.0],
                            metadata={"bbl": ["1", "0"]})
    assert "bbl" not in cube.metadata
