"""`mehs export` as one set: an interrupted export leaves no partial set that looks complete,
and a rerun replaces an earlier export without touching files it did not write.

Truth: the values each cube was filled with, read back with the OpenEXR module directly.
"""

import json

import numpy as np
import OpenEXR
import pytest

import mehs.export as ex
from mehs.cli import main
from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.io.envi import write_envi

WL31 = np.arange(400.0, 701.0, 10.0)


def _cube(value: float) -> SpectralCube:
    return SpectralCube(np.full((3, 4, 31), value, np.float32), WL31, units="relative radiance")


def _hdr(tmp_path, value: float):
    return write_envi(tmp_path / "in" / f"c{int(value)}.hdr", _cube(value), dtype="float32",
                      data_ext=".dat")


def _value(path) -> float:
    """The one value of a band / spectral file, read by OpenEXR itself (not mehs)."""
    ch = OpenEXR.File(str(path), separate_channels=True).channels()
    vals = {float(v) for c in ch.values() for v in np.unique(c.pixels)}
    assert len(vals) == 1, (path, vals)
    return vals.pop()


def _fail_at(monkeypatch, name: str, call: int):
    real = getattr(ex, name)
    count = [0]

    def failing(*a, **k):
        count[0] += 1
        if count[0] == call:
            raise OSError(28, "No space left on device")
        return real(*a, **k)

    monkeypatch.setattr(ex, name, failing)


def _no_hidden_leftovers(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".") and ".part" in p.name]


def test_interrupted_reexport_keeps_the_earlier_set_whole(tmp_path, monkeypatch):
    out = tmp_path / "env"
    ex.export_per_wavelength(_cube(1.0), out)
    listing = (out / "band_wavelengths.json").read_text()
    _fail_at(monkeypatch, "write_exr_gray", 18)           # file 17 (0-based) fails
    with pytest.raises(OSError):
        ex.export_per_wavelength(_cube(2.0), out)
    # before: bands 0..16 held the new cube, 17..30 the old one, under the old listing
    assert [_value(out / f"band_{i:03d}.exr") for i in range(31)] == [1.0] * 31
    assert (out / "band_wavelengths.json").read_text() == listing
    assert _no_hidden_leftovers(out) == []


def test_interrupted_first_export_leaves_no_bands(tmp_path, monkeypatch):
    out = tmp_path / "env"
    _fail_at(monkeypatch, "write_exr_gray", 18)
    with pytest.raises(OSError):
        ex.export_per_wavelength(_cube(2.0), out)
    assert sorted(p.name for p in out.iterdir()) == []     # before: band_000 … band_016


def test_cli_failure_in_the_spectral_file_keeps_the_earlier_export(tmp_path, monkeypatch, capsys):
    out = tmp_path / "exr"
    assert main(["export", str(_hdr(tmp_path, 1.0)), "--out", str(out)]) == 0
    _fail_at(monkeypatch, "export_spectral_exr", 1)
    assert main(["export", str(_hdr(tmp_path, 2.0)), "--out", str(out), "--force"]) != 0
    # before: the 31 bands of the new cube beside the old cube's band.exr
    assert {_value(p) for p in out.glob("band*.exr")} == {1.0}
    assert len(list(out.glob("band_*.exr"))) == 31 and (out / "band.exr").is_file()
    assert _no_hidden_leftovers(out) == []


def test_forced_export_of_one_format_removes_the_other_of_the_earlier_export(tmp_path, capsys):
    out = tmp_path / "exr"
    assert main(["export", str(_hdr(tmp_path, 1.0)), "--out", str(out)]) == 0
    (out / "notes.txt").write_text("mine")
    assert main(["export", str(_hdr(tmp_path, 2.0)), "--out", str(out), "--format", "spectral",
                 "--force"]) == 0
    # before: the earlier cube's band_000 … band_030 and listing stayed beside the new band.exr
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "band.exr", "notes.txt"]
    assert _value(out / "band.exr") == 2.0
    assert main(["export", str(_hdr(tmp_path, 3.0)), "--out", str(out), "--format",
                 "per-wavelength", "--force"]) == 0
    assert not (out / "band.exr").exists()                # before: the 2.0 cube's band.exr
    assert {_value(p) for p in out.glob("band_*.exr")} == {3.0}
    assert json.loads((out / "band_wavelengths.json").read_text())["files"][-1] == "band_030.exr"


def test_a_file_named_like_a_band_but_not_exported_is_never_removed(tmp_path, capsys):
    out = tmp_path / "exr"
    assert main(["export", str(_hdr(tmp_path, 1.0)), "--out", str(out)]) == 0
    foreign = out / "band_2024.exr"                   # e.g. a year-stamped map of another tool
    OpenEXR.File({"type": OpenEXR.scanlineimage},
                 {"Y": np.full((2, 2), 7.0, np.float32)}).write(str(foreign))
    before = foreign.read_bytes()
    rc = main(["export", str(_hdr(tmp_path, 2.0)), "--out", str(out), "--force"])
    err_text = capsys.readouterr().err
    assert rc == 2 and "band_2024.exr" in err_text and "not written by" in err_text
    assert foreign.read_bytes() == before             # before: deleted as a "stale band"
    assert {_value(p) for p in out.glob("band_0*.exr")} == {1.0}   # nothing was written
    with pytest.raises(InputError, match="not written by mehs export") as err:
        ex.export_per_wavelength(_cube(2.0), out)
    assert str(err.value.path) == str(foreign)


def test_rerun_after_a_kill_while_the_bands_were_renamed_needs_no_force(tmp_path, capsys):
    # SIGKILL while the staged bands were renamed into place: some bands there, no listing
    # (it is written last), so nothing looks complete; the same command must finish the job
    from mehs.export import export_per_wavelength
    from mehs.io import load_cube

    out = tmp_path / "exr"
    export_per_wavelength(load_cube(_hdr(tmp_path, 1.0)), out)
    for f in ("band_wavelengths.json", "band_wavelengths.txt"):
        (out / f).unlink()
    for f in sorted(out.glob("band_*.exr"))[3:]:
        f.unlink()
    assert main(["export", str(_hdr(tmp_path, 2.0)), "--out", str(out),
                 "--format", "per-wavelength"]) == 0
    assert (out / "band_wavelengths.json").is_file()
    # a complete export is still refused without --force
    assert main(["export", str(_hdr(tmp_path, 2.0)), "--out", str(out),
                 "--format", "per-wavelength"]) == 2
    assert "use --force" in capsys.readouterr().err
