"""Specim IQ capture folders: write → read (mehs and plain SPy), finding, bad folders."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError
from mehs.io import find_captures, load_cube, read_specim_folder, write_specim_folder
from mehs.io.specim import SpecimCapture, make_preview

WL = np.round(np.linspace(397.32, 1003.58, 204), 2)


def make_capture(cid="444", lines=6, samples=5, seed=0, *, white=True, whitedark=False,
                 reflectance=True, preview=None) -> SpecimCapture:
    rng = np.random.default_rng(seed)
    meta = dict(integration_time_ms=10.0, acquisition_date="2018-11-22T13:05:09",
                default_bands=(69, 52, 18), binning=(1, 1))

    def cube(n, lo, hi, **kw):
        return SpectralCube(rng.integers(lo, hi, (n, samples, 204)).astype(np.uint16), WL,
                            **{**meta, **kw})

    raw = cube(lines, 0, 4096, metadata={"fps": "100", "sensor type": "SPECIM IQ"})
    refl = None
    if reflectance:
        refl = SpectralCube(rng.random((lines, samples, 204)).astype(np.float32), WL,
                            units="reflectance")
    return SpecimCapture(
        capture_id=cid, root=None, raw=raw, darkref=cube(1, 60, 90),
        whiteref=cube(1, 3000, 4000) if white else None,
        whitedarkref=cube(1, 60, 90) if whitedark else None, reflectance=refl,
        metadata={"integration_time": "10", "datetime": "2018-11-22 13:05:09",
                  "datacube_angle": "0"}, preview=preview)


def test_round_trip_all_parts(tmp_path):
    cap = make_capture(whitedark=True)
    out = write_specim_folder(tmp_path / "444", cap)
    assert out == tmp_path / "444"
    names = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert names == sorted([
        "444.png", "manifest.xml", "metadata/444.xml",
        "capture/444.hdr", "capture/444.raw",
        "capture/DARKREF_444.hdr", "capture/DARKREF_444.raw",
        "capture/WHITEREF_444.hdr", "capture/WHITEREF_444.raw",
        "capture/WHITEDARKREF_444.hdr", "capture/WHITEDARKREF_444.raw",
        "results/REFLECTANCE_444.hdr", "results/REFLECTANCE_444.dat",
        "results/REFLECTANCE_444.png"])
    back = read_specim_folder(out)
    assert back.capture_id == "444" and back.root == out
    for kind in ("raw", "darkref", "whiteref", "whitedarkref", "reflectance"):
        a, b = getattr(cap, kind), getattr(back, kind)
        assert b.data.dtype == a.data.dtype, kind
        np.testing.assert_array_equal(b.data, a.data, err_msg=kind)
        np.testing.assert_array_equal(b.wavelengths, WL)
    assert back.raw.integration_time_ms == 10.0
    assert back.raw.default_bands == (69, 52, 18)
    assert back.reflectance.units == "reflectance"
    assert back.metadata == cap.metadata
    assert back.preview.dtype == np.uint8 and back.preview.shape == (6, 5, 3)
    np.testing.assert_array_equal(back.preview, make_preview(cap.raw))
    assert "raw" in (out / "manifest.xml").read_text()


def test_plain_spy_reads_written_folder(tmp_path):
    import spectral.io.envi as spy_envi

    cap = make_capture()
    out = write_specim_folder(tmp_path / "cap", cap)
    img = spy_envi.open(str(out / "capture" / "444.hdr"))
    assert img.metadata["data type"] == "12" and img.metadata["interleave"] == "bil"
    assert img.metadata["byte order"] == "0"
    assert float(img.metadata["tint"]) == 10.0
    assert [int(b) for b in img.metadata["default bands"]] == [70, 53, 19]
    np.testing.assert_array_equal(np.asarray(img.bands.centers, float), WL)
    np.testing.assert_array_equal(img.open_memmap(interleave="bip"), cap.raw.data)
    dark = spy_envi.open(str(out / "capture" / "DARKREF_444.hdr"))
    assert dark.shape == (1, 5, 204)


def test_non_digit_id_given_preview_and_folder_name_differs(tmp_path):
    prev = np.zeros((6, 5, 3), np.uint8)
    prev[..., 0] = 200
    cap = make_capture("scene_A-01", white=False, reflectance=False, preview=prev)
    out = write_specim_folder(tmp_path / "exposures" / "0_12.5ms", cap)
    back = read_specim_folder(out)
    assert back.capture_id == "scene_A-01"
    assert back.whiteref is None and back.reflectance is None
    np.testing.assert_array_equal(back.preview, prev)


def test_read_without_manifest_uses_names(tmp_path):
    out = write_specim_folder(tmp_path / "x", make_capture("777"))
    (out / "manifest.xml").unlink()
    back = read_specim_folder(out)
    assert back.capture_id == "777" and back.darkref is not None


def test_refuses_overwrite_and_leaves_no_temp(tmp_path):
    cap = make_capture()
    out = write_specim_folder(tmp_path / "444", cap)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(InputError, match="refusing to overwrite an existing capture"):
        write_specim_folder(out, make_capture(seed=1))
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["444"]


def test_failed_write_leaves_nothing(tmp_path):
    cap = make_capture()
    bad = cap.raw.data.astype(np.float32)
    bad[0, 0, 0] = -5  # cannot be stored as uint16
    cap.raw = cap.raw.with_data(bad)
    with pytest.raises(InputError, match="do not fit in uint16"):
        write_specim_folder(tmp_path / "444", cap)
    assert list(tmp_path.iterdir()) == []


def test_invalid_id_and_mismatched_reference(tmp_path):
    with pytest.raises(InputError, match="invalid capture id"):
        write_specim_folder(tmp_path / "a", make_capture("a/b"))
    cap = make_capture()
    cap.darkref = SpectralCube(np.zeros((1, 4, 204), np.uint16), WL)
    with pytest.raises(FormatError, match="reference has 4 samples"):
        write_specim_folder(tmp_path / "b", cap)
    assert list(tmp_path.iterdir()) == []


def test_missing_raw_cube(tmp_path):
    out = write_specim_folder(tmp_path / "444", make_capture())
    (out / "capture" / "444.hdr").unlink()
    (out / "capture" / "444.raw").unlink()
    before = sorted(out.rglob("*"))
    with pytest.raises(FormatError, match=r"444: raw cube missing: capture/444\.hdr"):
        read_specim_folder(out)
    (out / "manifest.xml").unlink()
    with pytest.raises(FormatError, match=r"444: not a Specim IQ capture: no raw cube"):
        read_specim_folder(out)
    assert sorted(out.rglob("*")) == [p for p in before if p.name != "manifest.xml"]


def test_missing_dark_reference(tmp_path):
    out = write_specim_folder(tmp_path / "444", make_capture())
    for ext in ("hdr", "raw"):
        (out / "capture" / f"DARKREF_444.{ext}").unlink()
    with pytest.raises(FormatError, match=r"444: dark reference missing: "
                                          r"capture/DARKREF_444\.hdr not found"):
        read_specim_folder(out)
    back = read_specim_folder(out, require_dark=False)
    assert back.darkref is None and back.whiteref is not None


def test_folder_does_not_exist(tmp_path):
    with pytest.raises(InputError, match=r"nowhere: folder does not exist"):
        read_specim_folder(tmp_path / "nowhere")


def test_bad_cube_inside_folder_names_the_file(tmp_path):
    out = write_specim_folder(tmp_path / "444", make_capture())
    raw = out / "capture" / "WHITEREF_444.raw"
    raw.write_bytes(raw.read_bytes()[:-2])
    with pytest.raises(FormatError, match=r"WHITEREF_444\.raw: data file is truncated"):
        read_specim_folder(out)


def test_find_captures_sorted_and_not_inside(tmp_path):
    for rel, cid in (("b/2", "2"), ("a/1", "1"), ("a/deep/er/x", "x")):
        write_specim_folder(tmp_path / rel, make_capture(cid, lines=2, samples=2,
                                                          reflectance=False))
    (tmp_path / "a" / "notes").mkdir()
    hidden = tmp_path / ".x.part-123"
    shutil.copytree(tmp_path / "b" / "2", hidden)
    found = find_captures(tmp_path)
    assert found == [tmp_path / "a/1", tmp_path / "a/deep/er/x", tmp_path / "b/2"]
    assert find_captures(tmp_path / "a" / "1") == [tmp_path / "a" / "1"]
    assert find_captures(tmp_path / "a" / "notes") == []
    with pytest.raises(InputError, match="does not exist"):
        find_captures(tmp_path / "zzz")


def test_load_cube_dispatch(tmp_path):
    cap = make_capture()
    out = write_specim_folder(tmp_path / "444", cap)
    for ext in ("hdr", "raw"):  # load_cube does not need the dark reference
        (out / "capture" / f"DARKREF_444.{ext}").unlink()
    np.testing.assert_array_equal(load_cube(out).data, cap.raw.data)
    np.testing.assert_array_equal(load_cube(out / "capture" / "444.hdr").data, cap.raw.data)
    with pytest.raises(InputError, match="does not exist"):
        load_cube(tmp_path / "missing.hdr")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a Specim IQ capture"):
        load_cube(tmp_path / "empty")
    (tmp_path / "thing.txt").write_text("hello")
    with pytest.raises(FormatError, match="not a recognised cube"):
        load_cube(tmp_path / "thing.txt")


def test_load_cube_exr(tmp_path):
    exr = pytest.importorskip("mehs.io.exr")
    cube = SpectralCube(np.random.default_rng(0).random((3, 4, 5)).astype(np.float32),
                        [400, 450, 500, 550, 600])
    p = exr.write_exr_spectral(tmp_path / "s.exr", cube)
    back = load_cube(p)
    np.testing.assert_array_equal(back.data, cube.data)
    np.testing.assert_array_equal(back.wavelengths, cube.wavelengths)


def test_manifest_path_outside_folder_refused(tmp_path):
    out = write_specim_folder(tmp_path / "444", make_capture(reflectance=False))
    mf = out / "manifest.xml"
    mf.write_text(mf.read_text().replace(">capture/444.hdr<", ">../../etc/444.hdr<"))
    with pytest.raises(FormatError, match="points outside the capture folder"):
        read_specim_folder(out)


def test_scene_exposure_style_id(tmp_path):
    # the capture engineer names exposure captures after their folder, e.g. 0_12.5ms
    out = write_specim_folder(tmp_path / "exposures" / "0_12.5ms",
                              make_capture("0_12.5ms", reflectance=False))
    assert (out / "capture" / "0_12.5ms.raw").is_file()
    back = read_specim_folder(out)
    assert back.capture_id == "0_12.5ms"
    (out / "manifest.xml").unlink()  # ".5ms" must not be taken for a file extension
    assert read_specim_folder(out).capture_id == "0_12.5ms"


def test_overwrite_removes_the_old_captures_extra_parts(tmp_path):
    """Overwriting a capture that had a white reference and a reflectance with one that has
    neither leaves neither behind (the reader found them by their standard names)."""
    out = write_specim_folder(tmp_path / "444", make_capture(whitedark=True))
    new = make_capture(seed=1, white=False, reflectance=False)
    write_specim_folder(out, new, overwrite=True)
    back = read_specim_folder(out)
    assert back.whiteref is None and back.whitedarkref is None and back.reflectance is None
    np.testing.assert_array_equal(back.raw.data, new.raw.data)
    np.testing.assert_array_equal(back.darkref.data, new.darkref.data)
    names = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert not any("WHITE" in n or "REFLECTANCE" in n for n in names), names
