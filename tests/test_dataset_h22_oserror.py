"""A scene whose file the system will not read (permissions, a vanished file, a full disk)
fails with one line naming the file — no Python traceback — and is retried next run."""

import errno

import numpy as np

import mehs.io.atomic as atomic
from mehs.cube import SpectralCube
from mehs.dataset.build import build_from_hs
from mehs.io.envi import write_envi

WL31 = np.arange(400.0, 701.0, 10.0)


def test_unreadable_input_is_one_line_and_retried(tmp_path, monkeypatch, capsys):
    hdr = write_envi(tmp_path / "in" / "c.hdr",
                     SpectralCube(np.full((3, 4, 31), 0.5, np.float32), WL31), dtype=np.float32)
    # (the build hashes its inputs through atomic.sha256_files, which calls this)
    real = atomic.sha256_file

    def denied(path, *a, **k):
        if str(path).endswith("in/c.raw"):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(atomic, "sha256_file", denied)
    m = build_from_hs([hdr], tmp_path / "ds", workers=1, progress=False)
    entry = m["scenes"][0]
    err = capsys.readouterr().err
    assert entry["status"] == "fail" and entry["error"].endswith("c.raw: Permission denied")
    assert "Traceback" not in err and "c.raw: Permission denied" in err
    assert "traceback" not in entry["provenance"]["run"]
    monkeypatch.setattr(atomic, "sha256_file", real)       # the user fixed it
    m = build_from_hs([hdr], tmp_path / "ds", workers=1, progress=False)
    assert m["scenes"][0]["status"] == "pass"
