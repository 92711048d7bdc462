"""The two-rename folder swap (systems without an atomic exchange): concurrent writers and
killed swaps, as on Linux with ``renameat2(RENAME_EXCHANGE)``."""

import errno
import os
from pathlib import Path

import pytest

import mehs.io.dirswap as dirswap


@pytest.fixture(autouse=True)
def no_exchange(monkeypatch):
    monkeypatch.setattr(dirswap, "_exchange", lambda a, b: False)


def _folder(path: Path, name: str) -> Path:
    path.mkdir()
    (path / name).write_bytes(name.encode())
    return path


def _names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_another_writer_taking_the_destination_between_the_renames(tmp_path, monkeypatch):
    # A moved the previous folder aside; B's complete folder lands at dest before A's
    # second rename: A must not fail (a finished report lost), and the last one wins
    dest = _folder(tmp_path / "f", "prev.png")
    new_a = _folder(tmp_path / "a.part", "a.png")
    new_b = _folder(tmp_path / "b.part", "b.png")
    real = os.rename
    state = {"raced": False}

    def rename(src, dst):
        if Path(src) == new_a and not state["raced"]:
            state["raced"] = True
            real(new_b, dest)           # B's swap completes in between
        return real(src, dst)

    monkeypatch.setattr(dirswap.os, "rename", rename)
    dirswap.replace_folder(new_a, dest)
    assert _names(dest) == ["a.png"]
    assert _names(tmp_path) == ["f"]          # B's folder and the previous one discarded


def test_destination_gone_before_it_is_moved_aside(tmp_path, monkeypatch):
    # another writer moved the previous folder aside first: nothing to move, ours goes in
    dest = _folder(tmp_path / "f", "prev.png")
    new = _folder(tmp_path / "n.part", "n.png")
    real = os.rename

    def rename(src, dst):
        if Path(src) == dest and Path(dst).name.startswith("f.part-"):
            real(dest, tmp_path / "elsewhere")   # the other writer's aside
            raise FileNotFoundError(errno.ENOENT, "gone", str(src))
        return real(src, dst)

    monkeypatch.setattr(dirswap.os, "rename", rename)
    dirswap.replace_folder(new, dest)
    assert _names(dest) == ["n.png"]


def test_no_shared_aside_name_between_writers(tmp_path, monkeypatch):
    # the fixed <dest>.old of older versions: a second writer's remove_path(old) deleted
    # the first one's previous folder while it was still needed to put it back
    dest = _folder(tmp_path / "f", "prev.png")
    new = _folder(tmp_path / "n.part", "n.png")
    asides = []
    real = os.rename

    def rename(src, dst):
        if Path(src) == dest:
            asides.append(Path(dst).name)
        return real(src, dst)

    monkeypatch.setattr(dirswap.os, "rename", rename)
    dirswap.replace_folder(new, dest)
    assert len(asides) == 1 and asides[0] != "f.old"
    assert dirswap._temp_re(dest).fullmatch(asides[0])


def test_an_aside_left_by_a_killed_swap_is_a_dead_writers_temporary(tmp_path, monkeypatch):
    # killed between the renames: the previous folder sits under the writer's temporary
    # name, which the next run's stale clean-up removes once that process is gone
    dest = _folder(tmp_path / "f", "prev.png")
    aside = dirswap._aside_name(dest)
    os.rename(dest, aside)
    monkeypatch.setattr(dirswap, "_alive", lambda pid: False)
    assert dirswap.remove_stale_temp_folders(dest) == [aside]
    assert _names(tmp_path) == []


def test_an_unrelated_error_of_the_second_rename_is_raised_with_the_previous_put_back(
        tmp_path, monkeypatch):
    dest = _folder(tmp_path / "f", "prev.png")
    new = _folder(tmp_path / "n.part", "n.png")
    real = os.rename

    def rename(src, dst):
        if Path(src) == new:
            raise PermissionError(errno.EACCES, "Permission denied", str(dst))
        return real(src, dst)

    monkeypatch.setattr(dirswap.os, "rename", rename)
    with pytest.raises(PermissionError):
        dirswap.replace_folder(new, dest)
    assert _names(dest) == ["prev.png"]
    assert _names(tmp_path) == ["f", "n.part"]
