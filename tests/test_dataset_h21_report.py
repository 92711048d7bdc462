"""`mehs report` interrupted or rerun after a killed run: no half folder, the previous report kept."""

import os
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

    root = tmp_path_factory.mktemp("rep21")
    rng = np.random.default_rng(3)
    for i in range(2):
        cube = rng.random((8, 6, 31), dtype=np.float32) + np.float32(0.1)
        write_envi(root / "cubes" / f"c{i}.hdr", SpectralCube(cube, WAVELENGTHS_31))
    ds = root / "ds"
    build_from_hs([root / "cubes"], ds, workers=1, progress=False)
    return ds


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _leftovers(folder: Path) -> list[str]:
    # report_files.part (older versions) and report_files.part-<pid>-<host>-<random>
    return sorted(p.name for p in folder.iterdir()
                  if p.name.endswith((".part", ".old")) or ".part-" in p.name)


@pytest.fixture
def reported(dataset, tmp_path):
    """A complete report in its own folder: (page, snapshot of page + images)."""
    page = report.write_dataset_report(dataset, tmp_path / "rep" / "report.html")
    return page, _snapshot(page.parent)


@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError])
def test_interrupted_report_leaves_no_partial_folder_and_keeps_the_previous(
        dataset, reported, monkeypatch, exc):
    page, before = reported
    real = report._scene_figure
    calls = []

    def second_figure_fails(*a, **k):
        calls.append(1)
        if len(calls) == 2:       # mid-way: one scene's figure is drawn, the next is not
            raise exc("interrupted")
        return real(*a, **k)

    monkeypatch.setattr(report, "_scene_figure", second_figure_fails)
    with pytest.raises(exc):
        report.write_dataset_report(dataset, page)
    assert len(calls) == 2
    assert _leftovers(page.parent) == []
    assert _snapshot(page.parent) == before


def test_interrupted_swap_puts_the_previous_folder_back(tmp_path, monkeypatch):
    # where the system cannot exchange two names atomically: two renames, and an
    # interruption between them must not lose the previous folder
    monkeypatch.setattr(dirswap, "_exchange", lambda a, b: False)
    dest, new = tmp_path / "f", tmp_path / "f.part"
    dest.mkdir()
    (dest / "old.png").write_bytes(b"old")
    new.mkdir()
    (new / "new.png").write_bytes(b"new")
    real_rename = os.rename

    def rename(src, dst):
        if Path(src) == new:
            raise KeyboardInterrupt
        return real_rename(src, dst)

    monkeypatch.setattr(dirswap.os, "rename", rename)
    with pytest.raises(KeyboardInterrupt):
        dirswap.replace_folder(new, dest)
    assert (dest / "old.png").read_bytes() == b"old"
    assert not (tmp_path / "f.old").exists()


@pytest.mark.parametrize("exchange", [True, False], ids=["exchange", "two-renames"])
def test_replace_folder_puts_the_new_folder_in_place(tmp_path, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr(dirswap, "_exchange", lambda a, b: False)
    dest, new = tmp_path / "f", tmp_path / "f.part"
    dest.mkdir()
    (dest / "old.png").write_bytes(b"old")
    new.mkdir()
    (new / "new.png").write_bytes(b"new")
    dirswap.replace_folder(new, dest)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]
    assert sorted(p.name for p in dest.iterdir()) == ["new.png"]
    # and onto nothing: a first report
    other = tmp_path / "g.part"
    other.mkdir()
    dirswap.replace_folder(other, tmp_path / "g")
    assert (tmp_path / "g").is_dir() and not other.exists()


@pytest.mark.parametrize("stale", ["folder", "file", "link"])
def test_rerun_after_a_killed_report_succeeds(dataset, reported, tmp_path, stale):
    # SIGKILL cannot clean up: what it left under the .part name of older versions is no
    # output (this version's own names: tests/test_dataset_h21b_report.py)
    page, _ = reported
    part = page.parent / "report_files.part"
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "keep.txt").write_text("not ours")
    if stale == "folder":
        part.mkdir()
        (part / ".c0_figure.abc.part.png").write_bytes(b"\x89PNG half")
        (part / "sub").mkdir()
    elif stale == "file":
        part.write_bytes(b"half")
    else:
        part.symlink_to(outside, target_is_directory=True)
    out = report.write_dataset_report(dataset, page)
    assert out == page and _leftovers(page.parent) == []
    assert (page.parent / "report_files" / "overview.png").stat().st_size > 0
    assert (outside / "keep.txt").read_text() == "not ours"   # a link is removed, not followed


@pytest.mark.parametrize("when", ["between the renames", "removing the previous"])
def test_rerun_after_a_kill_during_a_two_rename_swap(dataset, reported, when):
    page, _ = reported
    files = page.parent / "report_files"
    if when == "between the renames":    # previous images renamed aside, new not in place
        files.rename(page.parent / "report_files.old")
    else:                                # new in place, previous half removed
        (page.parent / "report_files.old").mkdir()
        (page.parent / "report_files.old" / "c1_figure.png").write_bytes(b"\x89PNG")
    report.write_dataset_report(dataset, page)
    assert _leftovers(page.parent) == []
    assert (files / "overview.png").is_file()


@pytest.mark.parametrize("exchange", [True, False], ids=["exchange", "two-renames"])
def test_previous_folder_that_cannot_be_removed_does_not_undo_the_swap(tmp_path, monkeypatch,
                                                                       exchange):
    """The new folder is in place; failing to delete the old one is a warning, so that the
    caller goes on (the report's page is written beside its new images)."""
    from mehs.errors import MehsError

    if not exchange:
        monkeypatch.setattr(dirswap, "_exchange", lambda a, b: False)
    real = dirswap.remove_path

    def stubborn(path, what="leftover"):
        if what == "previous folder":
            raise MehsError("cannot remove the previous folder (Permission denied)", path)
        return real(path, what)

    monkeypatch.setattr(dirswap, "remove_path", stubborn)
    dest, new = tmp_path / "f", tmp_path / "f.part"
    dest.mkdir()
    (dest / "old.png").write_bytes(b"old")
    new.mkdir()
    (new / "new.png").write_bytes(b"new")
    with pytest.warns(RuntimeWarning, match="new folder is in place"):
        dirswap.replace_folder(new, dest)
    assert sorted(p.name for p in dest.iterdir()) == ["new.png"]
