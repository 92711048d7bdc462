"""What the ``mehs`` command tells a user about its environment and its results.

- ``mehs --version`` and ``mehs info`` (no path) give the versions a bug report needs and,
  for each optional extra, whether it is installed or the command that installs it.
- A Python warning reaches the user as one ``mehs: warning:`` line, never as a source
  location followed by a line of mehs's code.
- ``mehs paper`` without the torch extra says why its tables hold no network.
- ``mehs evaluate`` on a dataset without a test or val split says that every scene,
  the training scenes included, was scored.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from mehs.cli import EXTRAS, main, versions_text
from mehs.ssr.synthetic import make_paired_set


def _mehs(*args, cwd=None):
    # the console entry point (python -m mehs), as a user runs it
    return subprocess.run([sys.executable, "-m", "mehs", *map(str, args)], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


def test_version_names_python_libraries_and_every_extra():
    r = _mehs("--version")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert out.startswith("mehs ")
    assert "Python 3." in out and "numpy " in out and "numba " in out
    for extra, _ in EXTRAS:
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(extra + " "))
        assert "installed (" in line or f'pip install -e ".[{extra}]"' in line, line


def test_version_reports_a_missing_extra_with_its_install_command(monkeypatch):
    from importlib import metadata

    real = metadata.version

    def fake(dist):
        if dist == "torch":
            raise metadata.PackageNotFoundError(dist)
        return real(dist)

    monkeypatch.setattr(metadata, "version", fake)
    text = versions_text()
    assert 'torch   not installed: python -m pip install -e ".[torch]"' in text


def test_info_without_a_path_prints_the_versions(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("mehs ") and "extras:" in out


def _header_without_byte_order(tmp_path):
    from mehs.cube import SpectralCube
    from mehs.io import write_envi
    from mehs.rgb import WAVELENGTHS_31

    path = tmp_path / "cube.hdr"
    data = np.random.default_rng(1).uniform(0.1, 1.0, (4, 3, 31)).astype(np.float32)
    write_envi(path, SpectralCube(data, WAVELENGTHS_31.astype(np.float64)))
    text = path.read_text()
    path.write_text("".join(ln for ln in text.splitlines(keepends=True)
                            if not ln.startswith("byte order")))
    return path


@pytest.mark.parametrize("command", ["info", "resample"])
def test_a_python_warning_is_one_mehs_line_without_source_code(tmp_path, command):
    """An ENVI header without 'byte order' warns (the reader assumes little-endian): the
    user saw '/…/mehs/cli/info.py:146: UserWarning: …' and the code line under it."""
    hdr = _header_without_byte_order(tmp_path)
    args = [command, hdr] + ([tmp_path / "out.hdr"] if command == "resample" else [])
    r = _mehs(*args)
    assert r.returncode == 0, r.stderr
    assert "mehs: warning: " in r.stderr and "no 'byte order' key" in r.stderr, r.stderr
    assert "UserWarning" not in r.stderr and ".py:" not in r.stderr, r.stderr
    assert "read_envi_header(" not in r.stderr, r.stderr


def test_show_warning_keeps_a_foreign_category_name(capsys):
    from mehs.cli import show_warning

    show_warning(RuntimeWarning("invalid value encountered"), RuntimeWarning, "x.py", 3)
    show_warning(UserWarning("a.hdr: something"), UserWarning, "x.py", 3)
    err = capsys.readouterr().err.splitlines()
    assert err == ["mehs: warning: RuntimeWarning: invalid value encountered",
                   "mehs: warning: a.hdr: something"]


def test_paper_without_networks_says_which_extra_gives_them(tmp_path, capsys, monkeypatch):
    import mehs.ssr.registry as registry

    ds = make_paired_set(tmp_path / "ds", n_scenes=3, size=8, seed=2)
    monkeypatch.setattr(registry, "list_architectures", lambda: {})
    assert main(["paper", str(ds), "--out", str(tmp_path / "p"), "--quick",
                 "--timing-size", "16x16", "--no-progress"]) == 0
    cap = capsys.readouterr()
    for stream in (cap.err, cap.out):
        assert "no SSR network to train" in stream
        assert '".[torch]"' in stream


def test_evaluate_says_when_every_scene_was_scored_train_included(tmp_path, capsys):
    ds = make_paired_set(tmp_path / "ds", n_scenes=1, size=8, seed=4)   # a train split only
    assert main(["evaluate", str(ds), "--models", "smits", "--out", str(tmp_path / "e")]) == 0
    out = capsys.readouterr().out
    assert "no test or val split" in out and "of its train split included" in out
    # a dataset with a test split: scored on it, no such note
    ds2 = make_paired_set(tmp_path / "ds2", n_scenes=3, size=8, seed=4)
    assert main(["evaluate", str(ds2), "--models", "smits", "--out", str(tmp_path / "e2")]) == 0
    assert "no test or val split" not in capsys.readouterr().out
