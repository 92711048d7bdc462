"""One simulated GigE Vision camera per interface and host: a cross-process lock on GVCP port 3956.

Aravis's fake camera (``ArvGvFakeCamera``) binds GVCP's fixed UDP port on its
interface address; Aravis offers no other port, and its discovery and control
of a camera at an address always use that one. So two simulators on one host —
two test runs at once, a developer's ``mehs sim-device --genicam`` beside CI —
cannot both serve. :class:`GvcpPortLock` makes them take turns (or fail at
once with a message naming the other process) instead of interfering silently.

References
----------
AIA, *GigE Vision 2.0*, 2011, §7 (GVCP on UDP port 3956). Aravis 0.8.26,
``src/arvgvfakecamera.c`` (``arv_gv_fake_camera_start``: the bind results are
not checked and ``is_running`` is set regardless).
"""

from __future__ import annotations

import errno
import fcntl
import ipaddress
import os
import re
import socket
import tempfile
import time
from pathlib import Path

from mehs.errors import DeviceError, InputError

#: GVCP's UDP port (GigE Vision 2.0 §7): Aravis's fake camera binds it on its interface address,
#: with no option to change it, and Aravis's device discovery and control talk to it only there.
GVCP_PORT = 3956
#: Environment variable: seconds to wait for another process's simulated camera to give the port
#: back (default 0: fail at once, naming that process). The GigE Vision tests set it, so that two
#: test runs on one host take turns instead of failing each other.
WAIT_ENV = "MEHS_GVCP_WAIT_S"

_held_here: set[str] = set()     # GVCP addresses this process serves a simulated camera on


class GvcpPortLock:
    """Cross-process lock on GVCP port 3956 of one interface, held while a simulated camera serves it.

    Aravis 0.8.26's fake camera ignores a failed bind of its GVCP socket and still reports
    ``is_running()``; its broadcast-discovery socket (SO_REUSEADDR) binds anyway, so a second
    fake camera answers discovery while the first one's GVCP socket answers its control: a client
    then silently drives the other process's camera. An ``flock`` on a file in the temporary
    directory (``/tmp``) serialises the simulators of every process on the host (the kernel releases it
    when a process dies, even killed), and a test bind of the port catches a camera that is not
    mehs's (``arv-fake-gv-camera-0.8``).
    """

    def __init__(self, interface: str, wait_s: float | None = None):
        self.interface = str(interface)
        if wait_s is None:
            try:
                wait_s = float(os.environ.get(WAIT_ENV) or 0.0)
            except ValueError:
                raise InputError(f"{WAIT_ENV}={os.environ[WAIT_ENV]!r} is not a number of seconds") from None
        self.wait_s = max(0.0, float(wait_s))
        safe = re.sub(r"[^0-9A-Za-z.]", "_", self.interface)
        # the port is the host's, not the user's: /tmp, not a per-user $TMPDIR, where there is one
        tmp = Path("/tmp") if Path("/tmp").is_dir() else Path(tempfile.gettempdir())
        self.path = tmp / f"mehs-gvcp-{safe}-{GVCP_PORT}.lock"
        self._fd: int | None = None

    def acquire(self) -> "GvcpPortLock":
        where = f"{self.interface}:{GVCP_PORT}"
        if self.interface in _held_here:
            raise DeviceError(f"this process already serves a simulated GigE Vision camera on {where}: "
                              "one at a time per interface (close the first)", where)
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except PermissionError:       # made by another user: a read-only descriptor locks as well
            fd = os.open(self.path, os.O_RDONLY)
        deadline = time.monotonic() + self.wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
            if time.monotonic() >= deadline:
                holder = self._holder(fd)
                os.close(fd)
                raise DeviceError(
                    f"another simulated GigE Vision camera ({holder}) serves {where}, and GVCP has one "
                    f"port per interface; waited {self.wait_s:g} s (set {WAIT_ENV} to wait longer, "
                    f"or stop that process; lock file {self.path})", where)
            time.sleep(0.05)
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:
            pass                      # read-only lock file: the holder goes unnamed
        self._fd = fd
        _held_here.add(self.interface)
        try:
            self._check_port_free()
        except BaseException:
            self.release()
            raise
        return self

    def _holder(self, fd: int) -> str:
        try:
            pid = os.pread(fd, 32, 0).decode().strip()
        except OSError:
            pid = ""
        return f"process {pid}" if pid.isdigit() else "another process"

    def _check_port_free(self) -> None:
        # Aravis would not say that its GVCP bind failed (see the class doc): bind it here first.
        try:
            ip = str(ipaddress.IPv4Address(self.interface))
        except ValueError:
            return                    # an interface name: its address is Aravis's to find
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.bind((ip, GVCP_PORT))
        except OSError as exc:
            raise DeviceError(f"UDP port {GVCP_PORT} on {ip} is already in use ({exc.strerror}): another "
                              "GigE Vision camera or simulator (arv-fake-gv-camera-0.8?) serves it, and "
                              "GVCP has one port per interface", f"{ip}:{GVCP_PORT}") from None
        finally:
            s.close()

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            _held_here.discard(self.interface)
            try:
                fcntl.flock(fd, fcntl.LOCK_UN)
            finally:
                os.close(fd)
