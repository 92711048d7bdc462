"""Two `mehs report` runs on one dataset at once: each has its own temporary folder.

With one fixed ``report_files.part`` name, a second run's start-up cleanup (or its failure
handler) deleted the first run's folder while it was being drawn.
"""

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import mehs.dataset.report as report
import mehs.io.dirswap as dirswap
from mehs.dataset.build import build_from_hs


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from mehs.cube import SpectralCube
    from mehs.io.envi import write_envi
    from mehs.rgb import WAVELENGTHS_31

    root = tmp_path_factory.mktemp("rep21b")
    rng = np.random.default_rng(5)
    for i in range(2):
        cube = rng.random((8, 6, 31), dtype=np.float32) + np.float32(0.1)
        write_envi(root / "cubes" / f"c{i}.hdr", SpectralCube(cube, WAVELENGTHS_31))
    ds = root / "ds"
    build_from_hs([root / "cubes"], ds, workers=1, progress=False)
    return ds


def _temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".part" in p.name or p.name.endswith(".old"))


@pytest.mark.parametrize("second", ["completes", "fails"])
def test_a_second_report_started_meanwhile_leaves_the_first_ones_folder(dataset, tmp_path,
                                                                        monkeypatch, second):
    page = tmp_path / "rep" / "report.html"
    real = report._scene_figure
    calls = []

    def figure(*a, **k):
        calls.append(1)
        if len(calls) == 1:
            # the first run has drawn its first thumbnail; a second run starts and ends
            if second == "completes":
                report.write_dataset_report(dataset, page)
            else:
                with pytest.raises(RuntimeError):
                    report.write_dataset_report(dataset, page)
        elif second == "fails" and len(calls) == 2:    # the second run's first figure
            raise RuntimeError("the second run's error")
        return real(*a, **k)

    monkeypatch.setattr(report, "_scene_figure", figure)
    out = report.write_dataset_report(dataset, page)   # the first run completes too
    assert out == page
    files = page.parent / "report_files"
    names = sorted(p.name for p in files.iterdir())
    assert names == ["c0_figure.png", "c0_thumb.png", "c1_figure.png", "c1_thumb.png",
                     "overview.png"]
    assert all((files / n).stat().st_size > 0 for n in names)
    assert _temporaries(page.parent) == []


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _rename_pid(tmp: Path, pid: int, host: str | None = None) -> Path:
    name, rest = tmp.name.split(".part-", 1)
    _, tag, rand = rest.split("-")
    new = tmp.with_name(f"{name}.part-{pid}-{host or tag}-{rand}")
    tmp.rename(new)
    return new


def test_startup_removes_only_dead_or_old_runs_temporaries(dataset, tmp_path):
    page = tmp_path / "rep" / "report.html"
    files = page.parent / "report_files"
    live = dirswap.make_temp_folder(files)                         # this process: running
    (live / "c0_thumb.png").write_bytes(b"\x89PNG drawing")
    parent_run = _rename_pid(dirswap.make_temp_folder(files), os.getppid())
    dead = _rename_pid(dirswap.make_temp_folder(files), _dead_pid())
    (dead / "c0_thumb.png").write_bytes(b"\x89PNG half")
    old = _rename_pid(dirswap.make_temp_folder(files), os.getppid())
    day_ago = time.time() - dirswap.STALE_AFTER_S - 60
    os.utime(old, (day_ago, day_ago))                              # its pid reused since
    other_host = _rename_pid(dirswap.make_temp_folder(files), _dead_pid(), "0badc0de")
    other_host_old = _rename_pid(dirswap.make_temp_folder(files), _dead_pid(), "0badc0de")
    os.utime(other_host_old, (day_ago, day_ago))
    legacy = page.parent / "report_files.part"                     # older versions' name
    legacy.mkdir()
    unrelated = page.parent / "report_files.partial-notes"
    unrelated.mkdir()

    report.write_dataset_report(dataset, page)
    left = set(_temporaries(page.parent))
    assert left == {live.name, parent_run.name, other_host.name, unrelated.name}
    assert (live / "c0_thumb.png").read_bytes() == b"\x89PNG drawing"
    assert (files / "overview.png").stat().st_size > 0


def test_temporary_folder_is_unique_and_has_the_usual_permissions(tmp_path):
    dest = tmp_path / "sub" / "f"
    a, b = dirswap.make_temp_folder(dest), dirswap.make_temp_folder(dest)
    assert a != b and a.is_dir() and b.is_dir()
    assert a.name.startswith(f"f.part-{os.getpid()}-")
    umask = os.umask(0o022)
    os.umask(umask)
    assert a.stat().st_mode & 0o777 == 0o777 & ~umask   # not mkdtemp's 0700: it becomes output
