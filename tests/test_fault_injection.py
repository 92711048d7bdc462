"""Fault injection on the CLI: a failed write names the file, and leaves nothing behind.

Disk full, I/O errors and refused renames are simulated by monkeypatching the
calls the writers make; the command must exit 2 with a message naming the output
the user asked for (not the hidden temporary file, and not no file at all).
"""

import errno
import os

import numpy as np
import pytest

from mehs.cli import main
from mehs.cube import SpectralCube
from mehs.io.envi import write_envi


@pytest.fixture()
def cube_hdr(tmp_path):
    rng = np.random.default_rng(0)
    cube = SpectralCube(rng.uniform(0.1, 1.0, (4, 5, 7)).astype(np.float32),
                        np.linspace(400, 700, 7), units="relative radiance")
    return write_envi(tmp_path / "in" / "c.hdr", cube, dtype="float32", data_ext=".dat")


def _enospc(*_a, **_k):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_disk_full_names_the_output(cube_hdr, tmp_path, monkeypatch, capsys):
    import mehs.io.envi_write as ew

    monkeypatch.setattr(ew, "_write_data", _enospc)
    out = tmp_path / "out" / "r.hdr"
    out.parent.mkdir()
    assert main(["resample", str(cube_hdr), str(out)]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and str(out.with_suffix(".dat")) in err, err
    assert "Traceback" not in err
    assert list(out.parent.iterdir()) == []      # no temporary file left


def test_failed_fsync_names_the_output(cube_hdr, tmp_path, monkeypatch, capsys):
    out = tmp_path / "rgb"
    monkeypatch.setattr(os, "fsync", _enospc)
    assert main(["rgb", str(cube_hdr), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    # every output is synced before its rename: the first one written (the EXR) fails
    assert "No space left on device" in err and str(out / "hdr_rgb.exr") in err, err
    # nothing was completed, so the --out folder this run created is gone too
    assert not out.exists() or not [p for p in out.iterdir() if ".part" in p.name]


def test_failed_rename_names_the_target_not_the_temporary(cube_hdr, tmp_path, monkeypatch,
                                                           capsys):
    real = os.replace

    def exdev(a, b):
        if str(b).endswith("hdr_rgb.exr"):
            raise OSError(errno.EXDEV, os.strerror(errno.EXDEV), a, b)
        return real(a, b)

    monkeypatch.setattr(os, "replace", exdev)
    out = tmp_path / "rgb"
    assert main(["rgb", str(cube_hdr), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"mehs: error: {out / 'hdr_rgb.exr'}: {os.strerror(errno.EXDEV)}", err
    assert not out.exists()      # nothing was written: the folder the run made is gone too


def test_unwritable_folder_names_the_output(tmp_path, monkeypatch, capsys):
    """As root a read-only folder is writable, so mkstemp's refusal is simulated."""
    import tempfile

    from mehs.io.atomic import write_json_atomic

    real = tempfile.mkstemp

    def refuse(*a, **k):
        fd, name = real(*a, **k)
        os.close(fd)
        os.unlink(name)
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), name)

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    target = tmp_path / "x.json"
    with pytest.raises(PermissionError) as info:
        write_json_atomic(target, {"a": 1})
    assert info.value.filename == str(target)
    assert list(tmp_path.iterdir()) == []



@pytest.fixture()
def dataset(cube_hdr, tmp_path):
    ds = tmp_path / "ds"
    assert main(["build", "--from-hs", str(cube_hdr), "--out", str(ds), "-q", "-j", "1"]) == 0
    return ds


def _damage(ds, fn):
    import json

    m = json.loads((ds / "manifest.json").read_text())
    fn(m["scenes"][0])
    (ds / "manifest.json").write_text(json.dumps(m))


@pytest.mark.parametrize("bad", [5, "x", [1], [1.5, 2], None])
def test_damaged_stat_record_is_hashed_not_a_traceback(cube_hdr, dataset, tmp_path, bad,
                                                        capsys):
    """A damaged ``output_stat`` is no cache: the files are hashed, and still match."""
    def hit(entry):
        st = entry["provenance"]["run"]["output_stat"]
        for k in st:
            st[k] = bad

    _damage(dataset, hit)
    assert main(["evaluate", str(dataset), "--models", "smits", "--out", str(tmp_path / "ev"),
                 "--split", "all", "--preprocess", "off"]) == 0
    commits = []
    from mehs.dataset.build import build_from_hs

    build_from_hs([cube_hdr], dataset, workers=1, progress=False, on_commit=commits.append)
    assert commits == []                            # intact outputs reused, not rebuilt
    assert "Traceback" not in capsys.readouterr().err


def test_damaged_file_path_is_named_and_the_scene_rebuilt(cube_hdr, dataset, capsys):
    def hit(entry):
        entry["files"]["hs_data"] = 7

    _damage(dataset, hit)
    capsys.readouterr()
    assert main(["build", "--from-hs", str(cube_hdr), "--out", str(dataset), "-q", "-j", "1"]) == 0
    err = capsys.readouterr().err
    assert "'hs_data' has no file path in manifest.json" in err and "rebuilding" in err, err


# ---------------------------------------------------------------------------------------
# Outputs that would replace or mix into inputs: raw captures, a command's own input given
# as its data file, a dataset, an earlier export's extra files.

SIM = ["--simulate", "--size", "8", "--no-progress"]


@pytest.fixture()
def capture(tmp_path):
    out = tmp_path / "scene"
    assert main(["capture", *SIM, "--times", "0.5,4", "--out", str(out)]) == 0
    return out


def test_resample_never_replaces_a_raw_capture(capture, capsys):
    exp = sorted((capture / "exposures").iterdir())[0]
    raw_hdr = exp / "capture" / f"{exp.name}.hdr"
    raw = raw_hdr.with_suffix(".raw")
    before = raw.read_bytes()
    rc = main(["resample", str(exp), str(raw_hdr), "--force"])
    assert rc == 2 and raw.is_file() and raw.read_bytes() == before


def test_resample_refuses_its_input_given_as_the_data_file(cube_hdr, capsys):
    data = cube_hdr.with_suffix(".dat")
    before = data.read_bytes()
    rc = main(["resample", str(data), str(cube_hdr), "--force"])
    assert rc == 2 and "overwrite the input" in capsys.readouterr().err
    assert data.read_bytes() == before


def test_forced_export_leaves_no_stale_band_files(cube_hdr, tmp_path):
    out = tmp_path / "exp"
    assert main(["export", str(cube_hdr), "--out", str(out), "--format", "per-wavelength"]) == 0
    assert main(["export", str(cube_hdr), "--out", str(out), "--format", "per-wavelength",
                 "--bands", "450:650:100", "--force"]) == 0
    assert sorted(p.name for p in out.glob("band_*.exr")) == [f"band_{i:03d}.exr"
                                                               for i in range(3)]


def test_evaluate_refuses_an_out_inside_the_dataset(cube_hdr, tmp_path, capsys):
    ds = tmp_path / "ds"
    assert main(["build", "--from-hs", str(cube_hdr), "--out", str(ds), "-q", "-j", "1"]) == 0
    sid = next(p.name for p in (ds / "scenes").iterdir())
    out = ds / "scenes" / sid
    rc = main(["evaluate", str(ds), "--models", "smits", "--out", str(out), "--split", "all",
               "--preprocess", "off"])
    assert rc == 2 and not (out / "evaluation.json").exists()


def test_no_command_writes_into_a_raw_capture_it_did_not_read(capture, cube_hdr, tmp_path,
                                                               capsys):
    exp = sorted((capture / "exposures").iterdir())[0]
    raw_hdr = exp / "capture" / f"{exp.name}.hdr"
    before = {p: p.read_bytes() for p in capture.rglob("*") if p.is_file()}
    # another cube resampled onto the raw header's name: the rewrite would drop its .raw
    assert main(["resample", str(cube_hdr), str(raw_hdr), "--force"]) == 2
    assert "raw capture" in capsys.readouterr().err
    assert main(["rgb", str(cube_hdr), "--out", str(exp / "rgb")]) == 2
    assert main(["export", str(cube_hdr), "--out", str(capture / "exp")]) == 2
    scene2 = tmp_path / "scene2"
    assert main(["capture", *SIM, "--times", "0.5,4", "--out", str(scene2)]) == 0
    assert main(["fuse", str(scene2), "--out", str(capture / "fused")]) == 2
    after = {p: p.read_bytes() for p in capture.rglob("*") if p.is_file()}
    assert after == before


def test_a_second_writer_into_one_output_folder_is_refused(cube_hdr, tmp_path, capsys):
    import subprocess
    import sys

    from mehs.io.lock import LOCK_NAME, OutputLock

    out = tmp_path / "rgb"
    # a live writer (another process) holds the folder: the second run is refused, and
    # leaves the folder as the first one will
    code = ("import sys, time; from mehs.io.lock import OutputLock\n"
            f"with OutputLock({str(out)!r}, what='mehs rgb'):\n"
            "    print('held', flush=True); sys.stdin.readline()\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(["rgb", str(cube_hdr), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "another 'mehs rgb'" in err and f"pid {holder.pid}" in err, err
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    finally:
        holder.communicate("\n", timeout=30)
    assert main(["rgb", str(cube_hdr), "--out", str(out)]) == 0
    assert not (out / LOCK_NAME).exists()
    # a lock left by a dead process is taken over
    (out / LOCK_NAME).write_text("999999999 " + os.uname().nodename + " mehs rgb\n")
    with OutputLock(out):
        pass


def test_a_killed_writers_temporary_files_go_with_the_next_run(cube_hdr, tmp_path):
    out = tmp_path / "rgb"
    out.mkdir()
    # what a SIGKILL between atomic_path's write and its rename leaves (the size of the data)
    left = [out / ".hdr_rgb.exr.k3j_x9.part.exr", out / ".mehs-write.lock.ab12.part"]
    for f in left:
        f.write_bytes(b"\0" * 1024)
    keep = out / "notes.txt"
    keep.write_text("mine")
    assert main(["rgb", str(cube_hdr), "--out", str(out)]) == 0
    assert not any(f.exists() for f in left) and keep.read_text() == "mine"
