"""`python -m mehs.ssr.net` without PyTorch: one line naming the extra, not a traceback;
importing the package keeps raising ImportError (callers test for it)."""

import subprocess
import sys


def _run(tmp_path, code_args):
    fake = tmp_path / "torch"
    fake.mkdir()
    (fake / "__init__.py").write_text('raise ImportError("No module named torch (hidden)")\n')
    env = {"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"}
    return subprocess.run([sys.executable, *code_args], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=120)


def test_module_run_without_torch_is_one_line(tmp_path):
    r = _run(tmp_path, ["-m", "mehs.ssr.net"])
    assert r.returncode == 1
    assert "Traceback" not in r.stderr and 'mehs[torch]' in r.stderr


def test_import_without_torch_still_raises_import_error(tmp_path):
    r = _run(tmp_path, ["-c", "import mehs.ssr.net"])
    assert r.returncode == 1 and "ImportError" in r.stderr and "mehs[torch]" in r.stderr
