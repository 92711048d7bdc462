"""Raw captures are never overwritten, even by a writer racing another one.

``atomic_path(..., overwrite=False)`` checked that the destination was absent and then
renamed onto it: a file another writer placed in between (a raw capture) was replaced.
"""

import pytest

import mehs.io.atomic as atomic
from mehs.errors import InputError


def test_a_raw_file_appearing_after_the_check_is_not_replaced(tmp_path, monkeypatch):
    dest = tmp_path / "capture.raw"
    real = atomic._fsync_file

    def other_writer_first(p):
        real(p)
        if not dest.exists():
            dest.write_bytes(b"the other writer's raw capture")

    monkeypatch.setattr(atomic, "_fsync_file", other_writer_first)
    with pytest.raises(InputError, match="refusing to overwrite"):
        atomic.write_bytes_atomic(dest, b"mine", overwrite=False)
    assert dest.read_bytes() == b"the other writer's raw capture"
    assert [p.name for p in tmp_path.iterdir()] == ["capture.raw"]      # no temporary left


def test_no_clobber_write_still_writes_a_new_file(tmp_path):
    dest = tmp_path / "a.raw"
    atomic.write_bytes_atomic(dest, b"x", overwrite=False)
    assert dest.read_bytes() == b"x" and [p.name for p in tmp_path.iterdir()] == ["a.raw"]
    assert dest.stat().st_nlink == 1
