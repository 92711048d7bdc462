import os
import stat

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.io.atomic import atomic_path, sha256_file, write_json_atomic, write_text_atomic


def test_atomic_write_leaves_no_temp_on_error(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("boom")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_refuses_to_overwrite_raw_capture(tmp_path):
    target = tmp_path / "raw.raw"
    write_text_atomic(target, "first")
    with pytest.raises(InputError, match="refusing to overwrite"):
        write_text_atomic(target, "second", overwrite=False)
    assert target.read_text() == "first"


def test_permissions_follow_umask(tmp_path):
    target = write_json_atomic(tmp_path / "a.json", {"b": 1})
    mode = stat.S_IMODE(os.stat(target).st_mode)
    mask = os.umask(0)
    os.umask(mask)
    assert mode == 0o666 & ~mask
    assert len(sha256_file(target)) == 64


@pytest.mark.parametrize("file_digest", [True, False])
@pytest.mark.parametrize("size", [0, 1, (1 << 18) - 1, 1 << 18, (1 << 18) + 1, 3 << 19])
def test_sha256_file_equals_hashlib(tmp_path, size, file_digest, monkeypatch):
    import hashlib

    if not file_digest:                      # the Python 3.10 path
        monkeypatch.delattr(hashlib, "file_digest", raising=False)
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    p = tmp_path / "f.raw"
    p.write_bytes(data)
    assert sha256_file(p) == hashlib.sha256(data).hexdigest()
