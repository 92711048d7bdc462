"""MATLAB ``.mat`` variables (v7.3 via :mod:`h5py`, v5 via :func:`scipy.io.loadmat`).

The lowest layer of the SSR dataset readers: :mod:`mehs.io.ssr_datasets`,
:mod:`mehs.io.ssr_harvard` and :mod:`mehs.io.ssr_kaist` all read their ``.mat`` files here,
so none of them has to import another for it; :func:`mat_variable_shapes` lists a file's
variables without reading their data (format detection, :mod:`mehs.ssr.sources`).

v7.3 files are HDF5 behind a 512-byte MATLAB userblock (MathWorks, "MAT-file versions");
their arrays are stored column-major, so every axis order is reversed on disk and is
reversed back here: a MATLAB ``H×W×B`` cube comes out ``(H, W, B)`` whichever version wrote
it. No hand-written parser.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mehs.errors import FormatError, InputError


def _is_hdf5(path: Path) -> bool:
    import h5py

    try:
        return bool(h5py.is_hdf5(str(path)))
    except OSError as exc:
        raise FormatError(f"cannot open ({exc})", path) from None


def read_mat_variables(path: str | Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Read ``keys`` from a MATLAB file (v7.3 via h5py, v5 via scipy.io) in MATLAB axis order.

    Raises
    ------
    InputError
        No such file.
    FormatError
        Unreadable or truncated file, or a key missing (the message names the key and lists
        the variables present).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    out: dict[str, np.ndarray] = {}
    if _is_hdf5(path):
        import h5py

        try:
            with h5py.File(path, "r") as f:
                for k in keys:
                    if k not in f:
                        raise FormatError(f"no variable {k!r} in the MATLAB v7.3 file "
                                          f"(variables: {', '.join(sorted(f.keys())) or 'none'})", path)
                    # column-major on disk: reversing the axes gives MATLAB's order
                    out[k] = np.asarray(f[k][()]).transpose()
        except FormatError:
            raise
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise FormatError(f"unreadable or truncated MATLAB v7.3 (HDF5) file ({exc})", path) from None
        return out
    import scipy.io
    from scipy.io.matlab import MatReadError

    if path.stat().st_size == 0:
        raise FormatError("empty file (an interrupted download?)", path)
    try:
        mat = scipy.io.loadmat(path, variable_names=list(keys))
        present = [n for n, *_ in scipy.io.whosmat(path)]
    except NotImplementedError as exc:
        raise FormatError(f"MATLAB file version not supported ({exc})", path) from None
    # (a short v5 file ends inside its header: scipy raises IndexError or MatReadError)
    except (MatReadError, ValueError, TypeError, OSError, EOFError, AssertionError,
            IndexError) as exc:
        raise FormatError(f"unreadable or truncated MATLAB file ({exc})", path) from None
    for k in keys:
        if k not in mat:
            raise FormatError(f"no variable {k!r} in the MATLAB file (variables: "
                              f"{', '.join(sorted(present)) or 'none'})", path)
        out[k] = np.asarray(mat[k])
    return out


def mat_variable_shapes(path: str | Path) -> dict[str, tuple[int, ...]]:
    """Variable names of a MATLAB file (v7.3 or v5) → their shapes in MATLAB's axis order.

    Reads headers only (no array data), so a folder of multi-GB cubes is probed in
    milliseconds. A struct or group (v7.3) has the shape ``()``.

    Parameters
    ----------
    path
        A ``.mat`` file.

    Returns
    -------
    dict
        ``{name: shape}``; empty when the file cannot be read (missing, truncated, not a
        MATLAB file): the callers guess a folder's format and must not stop at one bad
        file — reading it with :func:`read_mat_variables` names the problem.
    """
    import h5py
    from scipy.io.matlab import MatReadError

    try:
        if h5py.is_hdf5(str(path)):
            with h5py.File(path, "r") as h:
                # column-major on disk: the reversed shape is MATLAB's
                return {k: tuple(reversed(v.shape)) if isinstance(v, h5py.Dataset) else ()
                        for k, v in h.items()}
        import scipy.io

        return {n: tuple(shape) for n, shape, *_ in scipy.io.whosmat(path)}
    except (MatReadError, ValueError, TypeError, OSError, NotImplementedError, EOFError,
            IndexError, AssertionError):
        return {}
