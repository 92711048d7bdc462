"""ENVI reading/writing: round trips, files from the wild, bad input."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from mehs.cube import SpectralCube, UnsortedWavelengthsWarning
from mehs.errors import FormatError, InputError
from mehs.io import envi_write
from mehs.io.envi import (parse_acquisition_date, read_envi, read_envi_header,
                          write_envi)

WL = np.round(np.linspace(397.32, 1003.58, 204), 2)


def _cube(dtype=np.uint16, shape=(7, 5, 204), seed=0, **kw) -> SpectralCube:
    rng = np.random.default_rng(seed)
    if np.dtype(dtype).kind == "f":
        data = (rng.standard_normal(shape) * 1000).astype(dtype)
    elif np.dtype(dtype).kind == "i":
        data = rng.integers(-30000, 30000, shape).astype(dtype)
    else:
        data = rng.integers(0, 4096, shape).astype(dtype)
    wl = np.linspace(400, 1000, shape[2]) if shape[2] != 204 else WL
    kw.setdefault("fwhm", np.full(shape[2], 3.1))
    return SpectralCube(data, wl, **kw)


def write_raw_envi(folder: Path, name: str, data_file_order: np.ndarray, header: str,
                   *, offset_bytes: bytes = b"", ext: str = ".raw") -> Path:
    """A hand-made ENVI pair: ``header`` text verbatim, data bytes as given."""
    hp = folder / f"{name}.hdr"
    hp.write_text(header)
    (folder / f"{name}{ext}").write_bytes(offset_bytes + data_file_order.tobytes())
    return hp


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("interleave", ["bil", "bip", "bsq"])
@pytest.mark.parametrize("dtype", [np.uint16, np.int16, np.float32])
def test_round_trip_bit_exact(tmp_path, interleave, dtype):
    import spectral.io.envi as spy_envi

    cube = _cube(dtype, integration_time_ms=12.5, acquisition_date="2024-05-01T12:34:56",
                 default_bands=(69, 52, 18), binning=(1, 2),
                 metadata={"fps": "100", "sensor type": "SIM", "errors": ["none"]})
    hp = write_envi(tmp_path / "c.hdr", cube, interleave=interleave)
    back = read_envi(hp)
    assert back.data.dtype == np.dtype(dtype)
    assert back.data.shape == cube.data.shape
    np.testing.assert_array_equal(back.data, cube.data)
    np.testing.assert_array_equal(back.wavelengths, cube.wavelengths)
    np.testing.assert_array_equal(back.fwhm, cube.fwhm)
    assert back.integration_time_ms == 12.5
    assert back.acquisition_date == "2024-05-01T12:34:56"
    assert back.default_bands == (69, 52, 18)
    assert back.binning == (1, 2)
    assert back.metadata["fps"] == "100" and back.metadata["errors"] == ["none"]
    # plain SPy reads the same numbers and keys
    img = spy_envi.open(str(hp))
    np.testing.assert_array_equal(img.open_memmap(interleave="bip"), cube.data)
    assert float(img.metadata["tint"]) == 12.5
    assert [int(b) for b in img.metadata["default bands"]] == [70, 53, 19]
    np.testing.assert_array_equal(np.asarray(img.bands.centers), cube.wavelengths)


@pytest.mark.parametrize("interleave", ["bil", "bip", "bsq"])
def test_chunked_write_bit_exact(tmp_path, interleave, monkeypatch):
    # force many small chunks so the chunk boundaries are exercised
    monkeypatch.setattr(envi_write, "_CHUNK_BYTES", 997)
    cube = _cube(np.uint16, shape=(13, 11, 9))
    hp = write_envi(tmp_path / "c.hdr", cube, interleave=interleave)
    np.testing.assert_array_equal(read_envi(hp).data, cube.data)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
@pytest.mark.parametrize("interleave", ["bil", "bip", "bsq"])
def test_the_digest_hashed_while_writing_is_the_files(tmp_path, interleave, dtype,
                                                       monkeypatch):
    """Chunks are hashed on a thread while they are written: the SHA-256 handed back is
    that of the file's bytes (chunks in order, none twice), float data rounded into
    integers included."""
    import hashlib
    import threading

    monkeypatch.setattr(envi_write, "_CHUNK_BYTES", 997)
    cube = _cube(np.float32, shape=(19, 11, 9))
    cube.data[...] = np.abs(cube.data) * 10.3 % 60000.0
    digests = {}
    hp = write_envi(tmp_path / "c.hdr", cube, interleave=interleave, dtype=dtype,
                    data_ext=".dat", sha256=digests)
    data = hp.with_suffix(".dat")
    assert digests[data.name] == hashlib.sha256(data.read_bytes()).hexdigest()
    assert digests[hp.name] == hashlib.sha256(hp.read_bytes()).hexdigest()
    assert not [t for t in threading.enumerate() if t.name.startswith("mehs-sha256")]


def test_a_chunk_refused_midway_leaves_no_hashing_thread(tmp_path, monkeypatch):
    import threading

    from mehs.errors import InputError

    monkeypatch.setattr(envi_write, "_CHUNK_BYTES", 997)
    cube = _cube(np.float32, shape=(19, 11, 9))
    cube.data[...] = np.abs(cube.data)
    cube.data[15, 3, 2] = np.nan                     # in a late chunk: not an integer
    with pytest.raises(InputError, match="NaN"):
        write_envi(tmp_path / "c.hdr", cube, dtype=np.uint16, sha256={})
    assert not [t for t in threading.enumerate() if t.name.startswith("mehs-sha256")]
    assert not list(tmp_path.iterdir())              # nothing left as if complete


@pytest.mark.parametrize("sync_file_range", [True, False])
@pytest.mark.parametrize("interleave", ["bil", "bsq"])
def test_large_write_drops_its_page_cache_and_keeps_every_byte(tmp_path, interleave,
                                                               sync_file_range, monkeypatch):
    """Chunks written back and dropped as they go (Linux sync_file_range, or fdatasync
    elsewhere): the file is still bit-exact, and the dropper saw every chunk in order."""
    from mehs.io import streaming

    monkeypatch.setattr(envi_write, "_CHUNK_BYTES", 4000)
    monkeypatch.setattr(streaming, "DROP_CACHE_MIN_BYTES", 1)
    if not sync_file_range:
        monkeypatch.setattr(streaming, "_sync_file_range", None)
    seen = []
    real = streaming.CacheDropper.written

    def spy(self, offset, length):
        seen.append((offset, length))
        return real(self, offset, length)

    monkeypatch.setattr(streaming.CacheDropper, "written", spy)
    cube = _cube(np.float32, shape=(17, 13, 11))
    hp = write_envi(tmp_path / "c.hdr", cube, interleave=interleave, data_ext=".dat")
    np.testing.assert_array_equal(read_envi(hp).data, cube.data)
    assert len(seen) >= 3
    ends = np.cumsum([n for _, n in seen])
    assert [o for o, _ in seen] == [0, *ends[:-1]] and ends[-1] == cube.data.nbytes
    assert not list(tmp_path.glob(".*part*"))


def test_memmap_view_and_copy(tmp_path):
    cube = _cube(np.uint16, shape=(6, 4, 5))
    hp = write_envi(tmp_path / "c.hdr", cube, interleave="bil")
    mm = read_envi(hp).data
    assert isinstance(mm, np.memmap) and not mm.flags.writeable
    arr = read_envi(hp, memmap=False).data
    assert not isinstance(arr, np.memmap) and arr.flags.c_contiguous
    np.testing.assert_array_equal(arr, cube.data)


def test_read_by_data_file_and_other_extensions(tmp_path):
    cube = _cube(np.float32, shape=(3, 4, 5), units="reflectance", dark_subtracted=True)
    hp = write_envi(tmp_path / "r.hdr", cube, data_ext=".dat")
    assert (tmp_path / "r.dat").is_file()
    back = read_envi(tmp_path / "r.dat")
    np.testing.assert_array_equal(back.data, cube.data)
    assert back.units == "reflectance" and back.dark_subtracted
    assert back.source == hp
    write_envi(tmp_path / "n.hdr", cube, data_ext="")
    np.testing.assert_array_equal(read_envi(tmp_path / "n.hdr").data, cube.data)


def test_float_to_uint16_rounds_and_checks(tmp_path):
    data = np.array([[[0.4, 1.6, 4095.0]]], dtype=np.float32)
    cube = SpectralCube(data, [400.0, 500.0, 600.0])
    hp = write_envi(tmp_path / "a.hdr", cube, dtype=np.uint16)
    np.testing.assert_array_equal(read_envi(hp).data, [[[0, 2, 4095]]])
    for bad, msg in ((-1.0, "do not fit"), (70000.0, "do not fit"), (np.nan, "NaN")):
        d = data.copy()
        d[0, 0, 1] = bad
        with pytest.raises(InputError, match=msg) as ei:
            write_envi(tmp_path / "b.hdr", cube.with_data(d), dtype=np.uint16)
        assert "b.raw" in str(ei.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.hdr", "a.raw"]


def test_overwrite_false_refuses(tmp_path):
    cube = _cube(np.uint16, shape=(2, 2, 3))
    hp = write_envi(tmp_path / "c.hdr", cube, overwrite=False)
    before = hp.read_bytes(), (tmp_path / "c.raw").read_bytes()
    with pytest.raises(InputError, match="refusing to overwrite"):
        write_envi(hp, cube.with_data(cube.data + 1), overwrite=False)
    assert (hp.read_bytes(), (tmp_path / "c.raw").read_bytes()) == before
    write_envi(hp, cube.with_data(cube.data + 1))  # overwrite=True replaces
    np.testing.assert_array_equal(read_envi(hp).data, cube.data + 1)


def test_write_arguments_checked(tmp_path):
    cube = _cube(np.uint16, shape=(2, 2, 3))
    with pytest.raises(InputError, match="must end in .hdr"):
        write_envi(tmp_path / "c.raw", cube)
    with pytest.raises(InputError, match="interleave"):
        write_envi(tmp_path / "c.hdr", cube, interleave="xyz")
    with pytest.raises(InputError, match="float16 cannot be stored"):
        write_envi(tmp_path / "c.hdr", cube, dtype=np.float16)
    with pytest.raises(InputError, match="may not set 'samples'"):
        write_envi(tmp_path / "c.hdr", cube, extra_header={"Samples": 3})
    with pytest.raises(InputError, match="braces"):
        write_envi(tmp_path / "c.hdr", cube, extra_header={"note": "a}b"})
    assert list(tmp_path.iterdir()) == []


def test_extra_header_and_scale_factor_not_rewritten(tmp_path):
    cube = _cube(np.float32, shape=(2, 2, 3), metadata={"reflectance scale factor": 100.0})
    hp = write_envi(tmp_path / "c.hdr", cube, extra_header={"Sensor Type": "SPECIM IQ",
                                                            "gain": [1.0, 2.0, 3.5]})
    text = hp.read_text()
    assert "reflectance scale factor" not in text
    back = read_envi(hp)
    assert back.metadata["sensor type"] == "SPECIM IQ"
    assert back.metadata["gain"] == ["1.0", "2.0", "3.5"]


# ------------------------------------------------------------ files from the wild


def _hdr(samples, lines, bands, dtype_code, interleave, wl, extra=""):
    return (f"ENVI\nsamples = {samples}\nlines = {lines}\nbands = {bands}\n"
            f"data type = {dtype_code}\ninterleave = {interleave}\n"
            f"wavelength = {{{', '.join(str(w) for w in wl)}}}\n{extra}")


def test_big_endian_file(tmp_path):
    data = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5) * 97  # (L, S, B)
    file_order = data.transpose(0, 2, 1).astype(">u2")  # bil
    hp = write_raw_envi(tmp_path, "be", file_order,
                        _hdr(4, 3, 5, 12, "bil", [400, 500, 600, 700, 800], "byte order = 1\n"))
    cube = read_envi(hp)
    assert cube.data.dtype == np.dtype("uint16") and cube.data.dtype.isnative
    np.testing.assert_array_equal(cube.data, data)
    assert read_envi_header(hp).dtype == np.dtype(">u2")


def test_bip_int16_with_reflectance_scale_factor(tmp_path):
    rng = np.random.default_rng(3)
    data = rng.integers(0, 10000, (4, 3, 6)).astype(np.int16)
    hp = write_raw_envi(tmp_path, "refl", data.astype("<i2"),
                        _hdr(3, 4, 6, 2, "bip", [450, 500, 550, 600, 650, 700],
                             "byte order = 0\nreflectance scale factor = 10000\n"),
                        ext=".img")
    cube = read_envi(hp)
    assert cube.data.dtype == np.float32 and cube.units == "reflectance"
    np.testing.assert_allclose(cube.data, data / np.float32(10000), rtol=1e-7)
    assert cube.metadata["reflectance scale factor"] == 10000.0


def test_header_offset_and_bsq(tmp_path):
    data = np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4)
    hp = write_raw_envi(tmp_path, "off", data.transpose(2, 0, 1).astype("<f4"),
                        _hdr(3, 2, 4, 4, "bsq", [400, 410, 420, 430],
                             "byte order = 0\nheader offset = 128\n"),
                        offset_bytes=b"\xff" * 128, ext=".bsq")
    np.testing.assert_array_equal(read_envi(hp).data, data)


def test_capitalised_keys_and_values(tmp_path):
    data = np.arange(2 * 2 * 3, dtype=np.uint16).reshape(2, 2, 3)
    header = ("ENVI\nSamples = 2\nLines = 2\nBands = 3\nData Type = 12\nInterleave = BIL\n"
              "Byte Order = 0\nWavelength Units = Micrometers\n"
              "Wavelength = {0.4, 0.5, 0.6}\nFWHM = {0.01, 0.01, 0.01}\n"
              "Default Bands = {3, 2, 1}\nTINT = 7.5\n"
              "Acquisition Date = DATE(dd-mm-yyyy): 22-11-2018\n")
    hp = write_raw_envi(tmp_path, "caps", data.transpose(0, 2, 1).astype("<u2"), header)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SPy's lower-casing warning is not passed on
        cube = read_envi(hp)
    np.testing.assert_array_equal(cube.data, data)
    np.testing.assert_allclose(cube.wavelengths, [400, 500, 600])
    np.testing.assert_allclose(cube.fwhm, [10, 10, 10])
    assert cube.default_bands == (2, 1, 0)
    assert cube.integration_time_ms == 7.5
    assert cube.acquisition_date == "2018-11-22"


def test_unsorted_wavelengths_two_spectrometers(tmp_path):
    # VNIR 400..700 followed by SWIR 650..1000: overlapping, not sorted
    wl = [400, 500, 600, 700, 650, 800, 1000]
    data = np.arange(2 * 2 * 7, dtype=np.uint16).reshape(2, 2, 7)
    hp = write_raw_envi(tmp_path, "two", data.astype("<u2"),
                        _hdr(2, 2, 7, 12, "bip", wl, "byte order = 0\n"
                             "default bands = {4, 2, 1}\n"))
    with pytest.warns(UnsortedWavelengthsWarning):
        cube = read_envi(hp)
    order = np.argsort(wl)
    np.testing.assert_array_equal(cube.wavelengths, np.sort(wl))
    np.testing.assert_array_equal(cube.data, data[:, :, order])
    assert [cube.wavelengths[b] for b in cube.default_bands] == [700, 500, 400]


@pytest.mark.parametrize("text, iso", [
    ("22-11-2018", "2018-11-22"),
    ("2018-11-22", "2018-11-22"),
    ("DATE(dd-mm-yyyy): 22-11-2018", "2018-11-22"),
    ("DATE(dd-mm-yyyy): 22-11-2018 13:05:09", "2018-11-22T13:05:09"),
    ("DATE(yyyy-mm-dd): 2018-11-22 13:05", "2018-11-22T13:05:00"),
    ("2018-11-22T13:05:09.25", "2018-11-22T13:05:09.250000"),
    ("DATE(dd-mm-yyyy): 22-11-2018 13:05:09+00:00", "2018-11-22T13:05:09+00:00"),
    ("2018-11-22 13:05:09-0130", "2018-11-22T13:05:09-01:30"),
    ("DATE(dd-mm-yyyy): 32-11-2018", None),
    ("yesterday", None),
])
def test_acquisition_date_forms(text, iso):
    assert parse_acquisition_date(text) == iso


@pytest.mark.parametrize("iso", ["2018-11-22", "2018-11-22T13:05:09",
                                 "2026-11-24T06:17:00+00:00", "2018-11-22T13:05:09.125000"])
def test_acquisition_date_round_trip(tmp_path, iso):
    cube = SpectralCube(np.zeros((1, 1, 2), np.uint16), [400, 500], acquisition_date=iso)
    hp = write_envi(tmp_path / "d.hdr", cube)
    assert "DATE(dd-mm-yyyy): " in hp.read_text()
    assert read_envi(hp).acquisition_date == iso


@pytest.mark.parametrize("dtype", ["uint8", "int16", "int32", "float32", "float64",
                                   "complex64", "complex128", "uint16", "uint32", "int64",
                                   "uint64"])
def test_every_envi_data_type_round_trips(tmp_path, dtype):
    rng = np.random.default_rng(5)
    data = (rng.random((3, 4, 5)) * 200).astype(dtype)
    hp = write_envi(tmp_path / "t.hdr", SpectralCube(data, [400, 450, 500, 550, 600]),
                    interleave="bsq")
    back = read_envi(hp)
    assert back.data.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(back.data, data)


def test_failed_overwrite_keeps_old_pair(tmp_path):
    cube = SpectralCube(np.ones((2, 2, 3), np.float32), [400, 500, 600])
    hp = write_envi(tmp_path / "c.hdr", cube, dtype=np.uint16)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    bad = cube.data.copy()
    bad[1, 1, 1] = np.inf
    with pytest.raises(InputError, match="NaN/Inf"):
        write_envi(hp, cube.with_data(bad), dtype=np.uint16)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_unparseable_date_kept_with_warning(tmp_path):
    data = np.zeros((1, 1, 2), np.uint8)
    hp = write_raw_envi(tmp_path, "d", data, _hdr(1, 1, 2, 1, "bip", [400, 500],
                                                  "acquisition date = sometime\n"))
    with pytest.warns(UserWarning, match="not understood"):
        assert read_envi(hp).acquisition_date == "sometime"


def test_missing_byte_order_and_interleave_single_band(tmp_path):
    data = np.arange(6, dtype=np.uint16).reshape(2, 3, 1)
    hp = write_raw_envi(tmp_path, "one", data.astype("<u2"),
                        "ENVI\nsamples = 3\nlines = 2\nbands = 1\ndata type = 12\n"
                        "wavelength = {550}\n")
    with pytest.warns(UserWarning, match="assuming 0"):
        cube = read_envi(hp)
    np.testing.assert_array_equal(cube.data, data)


# ---------------------------------------------------------------------- bad input


def _good_pair(tmp_path, name="bad", extra="", wl=(400, 500, 600), bands=3,
               dtype_code=12, lines=2, samples=2, nbytes=None, keys_drop=()):
    lines_ = [f"samples = {samples}", f"lines = {lines}", f"bands = {bands}",
              f"data type = {dtype_code}", "interleave = bil", "byte order = 0",
              f"wavelength = {{{', '.join(str(w) for w in wl)}}}"]
    lines_ = [ln for ln in lines_ if ln.split(" =")[0] not in keys_drop]
    hp = tmp_path / f"{name}.hdr"
    hp.write_text("ENVI\n" + "\n".join(lines_) + "\n" + extra)
    n = 2 * 2 * 3 * 2 if nbytes is None else nbytes
    (tmp_path / f"{name}.raw").write_bytes(b"\x01" * n)
    return hp


BAD_CASES = {
    "truncated": (dict(nbytes=20), FormatError, r"bad\.raw: data file is truncated: "
                  r"expected 24 bytes .* found 20"),
    "missing_key": (dict(keys_drop=("samples",)), FormatError,
                    r"bad\.hdr: mandatory header key 'samples' is missing"),
    "unknown_dtype": (dict(dtype_code=7), FormatError, r"bad\.hdr: unknown ENVI data type '7'"),
    "band_count": (dict(wl=(400, 500)), FormatError,
                   r"bad\.hdr: 'wavelength' has 2 values for 3 bands"),
    "non_numeric_wl": (dict(wl=(400, "abc", 600)), FormatError,
                       r"bad\.hdr: 'wavelength' value 'abc' \(band 2\) is not a number"),
    "duplicate_wl": (dict(wl=(400, 500, 500)), FormatError,
                     r"bad\.hdr: 'wavelength': duplicate wavelengths \[500\.0\]"),
    "no_interleave": (dict(keys_drop=("interleave",)), FormatError,
                      r"bad\.hdr: mandatory header key 'interleave' is missing"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_raises_naming_file(tmp_path, case):
    kwargs, exc_type, pattern = BAD_CASES[case]
    hp = _good_pair(tmp_path, **kwargs)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(exc_type, match=pattern) as ei:
        read_envi(hp)
    assert str(tmp_path) in str(ei.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_path_does_not_exist(tmp_path):
    with pytest.raises(InputError, match=r"nope\.hdr: file does not exist"):
        read_envi(tmp_path / "nope.hdr")
    with pytest.raises(InputError, match=r"nope\.raw: file does not exist"):
        read_envi(tmp_path / "nope.raw")


def test_not_a_header_and_missing_data_file(tmp_path):
    p = tmp_path / "x.hdr"
    p.write_text("samples = 2\n")
    with pytest.raises(FormatError, match=r"x\.hdr: not an ENVI header"):
        read_envi(p)
    hp = _good_pair(tmp_path, name="nodata")
    (tmp_path / "nodata.raw").unlink()
    with pytest.raises(FormatError, match=r"nodata\.hdr: data file not found"):
        read_envi(hp)
    q = tmp_path / "lone.raw"
    q.write_bytes(b"\0" * 8)
    with pytest.raises(FormatError, match=r"lone\.raw: no ENVI header found"):
        read_envi(q)


def test_unclosed_brace_and_bad_numbers(tmp_path):
    hp = _good_pair(tmp_path, name="brace", extra="description = {never closed\n")
    with pytest.raises(FormatError, match=r"brace\.hdr: ENVI header cannot be parsed"):
        read_envi(hp)
    hp = _good_pair(tmp_path, name="tint", extra="tint = fast\n")
    with pytest.raises(FormatError, match=r"tint\.hdr: 'tint' = 'fast' is not a number"):
        read_envi(hp)
    hp = _good_pair(tmp_path, name="neg", keys_drop=("lines",), extra="lines = -2\n")
    with pytest.raises(FormatError, match=r"neg\.hdr: header key 'lines' = -2"):
        read_envi(hp)


def test_a_named_data_file_is_read_and_several_candidates_are_refused(tmp_path):
    """An ENVI header does not name its data file: ``read_envi("x.img")`` reads x.img, and
    ``x.hdr`` beside both x.raw and x.img is refused as ambiguous (mehs read x.raw, SPy
    x.img: one of them silently wrong)."""
    small = _cube(np.uint16, shape=(2, 3, 4))
    write_envi(tmp_path / "x.hdr", small)                       # x.raw
    nines = small.with_data(np.full(small.data.shape, 9, np.uint16))
    (tmp_path / "x.img").write_bytes(np.ascontiguousarray(
        nines.data.transpose(0, 2, 1)).astype("<u2").tobytes())  # the same layout (bil)
    np.testing.assert_array_equal(read_envi(tmp_path / "x.img").data, nines.data)
    np.testing.assert_array_equal(read_envi(tmp_path / "x.raw").data, small.data)
    with pytest.raises(FormatError, match="several files") as e:
        read_envi(tmp_path / "x.hdr")
    assert "x.raw" in str(e.value) and "x.img" in str(e.value)


def test_overwriting_with_another_data_extension_replaces_the_old_data(tmp_path):
    """Rewriting ``out.hdr`` with ``.dat`` over an ``out.raw`` pair removes out.raw (the old
    header's data), so the new pair reads back; a stray file of the stem that was not the
    old header's data is refused before anything is written."""
    ones = _cube(np.float32, shape=(2, 3, 4))
    sevens = ones.with_data(np.full(ones.data.shape, 7, np.float32))
    write_envi(tmp_path / "out.hdr", ones, data_ext=".raw")
    write_envi(tmp_path / "out.hdr", sevens, data_ext=".dat")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.dat", "out.hdr"]
    np.testing.assert_array_equal(read_envi(tmp_path / "out.hdr").data, sevens.data)
    (tmp_path / "new.img").write_bytes(b"someone else's")
    with pytest.raises(InputError, match="new.img would also read"):
        write_envi(tmp_path / "new.hdr", ones)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.img", "out.dat", "out.hdr"]


@pytest.mark.parametrize("unit,scale", [("Centimeters", 1e-7), ("cm", 1e-7), ("Meters", 1e-9),
                                        ("m", 1e-9), ("Angstroms", 10.0),
                                        ("Millimeters", 1e-6)])
def test_every_envi_length_unit_converts_to_nm(tmp_path, unit, scale):
    """The ENVI header spec's length units (SPy passes them through as stored)."""
    wl = np.array([400.0, 500.0, 600.0])
    hdr = ("ENVI\nsamples = 1\nlines = 1\nbands = 3\nheader offset = 0\ndata type = 4\n"
           "interleave = bip\nbyte order = 0\nwavelength units = " + unit + "\n"
           "wavelength = {" + ", ".join(repr(float(w * scale)) for w in wl) + "}\n")
    hp = write_raw_envi(tmp_path, "u", np.ones(3, "<f4"), hdr)
    np.testing.assert_allclose(read_envi(hp).wavelengths, wl, rtol=1e-9)
    bad = write_raw_envi(tmp_path, "w", np.ones(3, "<f4"),
                         hdr.replace(f"units = {unit}", "units = Wavenumber"))
    with pytest.raises(FormatError, match="Wavenumber"):
        read_envi(bad)


def test_float_to_integer_rounds_before_the_range_check(tmp_path):
    """"Round to nearest and must fit": -0.3 → 0 and 65535.3 → 65535 fit uint16; -0.6 → -1
    does not."""
    ok = np.array([[[-0.3, 65535.3, 2.5]]])
    hp = write_envi(tmp_path / "a.hdr", SpectralCube(ok, [400.0, 500.0, 600.0]),
                    dtype=np.uint16)
    np.testing.assert_array_equal(read_envi(hp).data, [[[0, 65535, 2]]])
    with pytest.raises(InputError, match="do not fit"):
        write_envi(tmp_path / "b.hdr", SpectralCube(ok - 0.3, [400.0, 500.0, 600.0]),
                   dtype=np.uint16)
