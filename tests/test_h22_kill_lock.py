"""The output lock after a SIGKILL: the kernel says whether its holder lives, not the pid.

A writer killed (SIGKILL, OOM, power loss) leaves its lock file behind. The next run must
take it over even when the pid written in it now belongs to a live process (a reboot, or
any pid reuse), and two runs recovering one stale lock at once must never both hold it.
"""

import os
import subprocess
import sys

import pytest

from mehs.errors import InputError
from mehs.io.lock import LOCK_NAME, OutputLock

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="POSIX flock")


def test_a_killed_writers_lock_whose_pid_was_reused_is_taken_over(tmp_path):
    # the dead writer's pid is now a live process's (here: this test's own parent)
    (tmp_path / LOCK_NAME).write_text(f"{os.getppid()} {os.uname().nodename} mehs fuse\n")
    with OutputLock(tmp_path, what="mehs fuse"):
        assert (tmp_path / LOCK_NAME).read_text().split()[0] == str(os.getpid())
    assert not (tmp_path / LOCK_NAME).exists()


def test_a_live_holder_in_another_process_is_still_refused(tmp_path):
    code = ("import sys; from mehs.io.lock import OutputLock\n"
            f"with OutputLock({str(tmp_path)!r}, what='mehs rgb'):\n"
            "    print('held', flush=True); sys.stdin.readline()\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match=f"pid {holder.pid}"):
            with OutputLock(tmp_path):
                pass
    finally:
        holder.communicate("\n", timeout=30)
    with OutputLock(tmp_path):          # released with its holder
        pass


def test_a_sigkilled_holders_lock_is_taken_over(tmp_path):
    code = ("import os, signal; from mehs.io.lock import OutputLock\n"
            f"l = OutputLock({str(tmp_path)!r}, what='mehs fuse').__enter__()\n"
            "os.kill(os.getpid(), signal.SIGKILL)\n")
    subprocess.run([sys.executable, "-c", code], timeout=60)
    assert (tmp_path / LOCK_NAME).exists()
    with OutputLock(tmp_path):
        pass


def test_two_runs_recovering_one_stale_lock_never_both_hold_it(tmp_path, monkeypatch):
    """B judges the dead writer's lock stale; before B removes it, A takes it over. B must
    then be refused, not remove A's new lock and hold the folder beside A."""
    (tmp_path / LOCK_NAME).write_text(f"999999999 {os.uname().nodename} mehs build\n")
    real = OutputLock._stale
    held, refused = [], []
    state = {"fired": False}

    def stale_then_a_runs(self, *a, **kw):
        verdict = real(self, *a, **kw)
        if not state["fired"]:
            state["fired"] = True          # A, inside, judges with the real rule
            other = OutputLock(tmp_path, what="A")
            try:
                held.append(other.__enter__())
            except InputError:
                refused.append("A")
        return verdict

    monkeypatch.setattr(OutputLock, "_stale", stale_then_a_runs)
    b = OutputLock(tmp_path, what="B")
    try:
        held.append(b.__enter__())
    except InputError:
        refused.append("B")
    try:
        assert len(held) == 1 and len(refused) == 1, (held, refused)
        owner = (tmp_path / LOCK_NAME).read_text().split()[2]
        assert owner == held[0].what
    finally:
        for lk in held:
            lk.__exit__(None, None, None)


def test_another_hosts_lock_is_kept(tmp_path):
    (tmp_path / LOCK_NAME).write_text("4242 some-other-host mehs build\n")
    with pytest.raises(InputError, match="on host some-other-host"):
        with OutputLock(tmp_path):
            pass


def test_a_holders_clean_up_of_a_waiting_runs_temporary_is_a_refusal_not_a_crash(
        tmp_path, monkeypatch):
    """The holder removes hidden ``*.part`` files (a killed writer's) when it takes the
    lock; one of them may be the lock temporary of a run about to be refused."""
    import mehs.io.lock as lk

    real_link = os.link
    held = []

    def holder_first(src, dst, *a, **kw):
        if not held:
            monkeypatch.setattr(lk.os, "link", real_link)
            held.append(OutputLock(tmp_path, what="A").__enter__())   # cleans up src
        return real_link(src, dst, *a, **kw)

    monkeypatch.setattr(lk.os, "link", holder_first)
    try:
        with pytest.raises(InputError, match="another 'A'"):
            with OutputLock(tmp_path, what="B"):
                pass
    finally:
        for h in held:
            h.__exit__(None, None, None)
