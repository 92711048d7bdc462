"""One exception family for the whole toolkit.

Every error a user can cause (bad file, bad argument, device fault) is a
:class:`MehsError`; the CLI prints its message without a traceback and exits
non-zero. Messages name the file (or device) and the problem.
"""

from __future__ import annotations

from pathlib import Path


class MehsError(Exception):
    """Base class of all errors mehs raises on purpose.

    Parameters
    ----------
    message
        What is wrong, phrased so a user can act on it.
    path
        The file, folder or device port concerned, if any; it is prefixed to
        the message.
    """

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = None if path is None else str(path)
        self.problem = message
        super().__init__(f"{self.path}: {message}" if self.path else message)

    def with_path(self, path: str | Path | None) -> "MehsError":
        """This error naming ``path``; unchanged if it already names a file.

        For library code that checks arrays (which know no file) called on a
        cube that came from one: ``except MehsError as e: raise e.with_path(src)``.
        """
        if self.path is not None or path is None:
            return self
        return type(self)(self.problem, path)


class InputError(MehsError, ValueError):
    """Bad input data or arguments: truncated files, wrong band counts, NaN, …"""


class FormatError(InputError):
    """A file does not follow the format it claims (ENVI, Specim IQ, OpenEXR)."""


class DeviceError(MehsError):
    """A device (stage, camera) reported a fault or broke its protocol."""


class DeviceTimeout(DeviceError):
    """A device did not answer in time."""


class DeviceDisconnected(DeviceError):
    """The connection to a device was lost."""


def first_line(message) -> str:
    """The first non-blank line of an exception's (or a text's) message, for a one-line
    error; an exception with no message gives its type's name."""
    lines = [ln.strip() for ln in str(message).splitlines() if ln.strip()]
    if lines:
        return lines[0]
    return type(message).__name__ if isinstance(message, BaseException) else "no message"
