"""The ``mehs`` command line.

Each sub-command lives in its own module ``mehs.cli.<name>`` exposing
``configure(parser)`` (add arguments; keep imports light) and ``run(args) -> int``
(do the work; import heavy libraries here). :class:`~mehs.errors.MehsError` is
printed as ``mehs: error: …`` without a traceback and exits with status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from mehs import __version__
from mehs.errors import MehsError

#: (sub-command, module under mehs.cli, one-line help) in pipeline order.
COMMANDS: list[tuple[str, str, str]] = [
    ("info", "info", "summarise an ENVI cube, a Specim IQ folder or an OpenEXR image"),
    ("sim-device", "sim_device", "start the simulated stage and camera and print their ports"),
    ("capture", "capture", "capture a bracketed scene (dark/white refs + exposures)"),
    ("calibrate", "calibrate", "radiometric calibration from a capture of a known reference"),
    ("fuse", "fuse", "recover the response curve and merge a bracket into an HDR cube"),
    ("resample", "resample", "resample a cube to a target band set (default 400:700:10)"),
    ("rgb", "rgb", "make pseudo-HDR-RGB (EXR), LDR-RGB (PNG) and previews of an HS cube"),
    ("export", "export", "export an HS cube for spectral rendering (EXR per wavelength)"),
    ("render", "render", "render an object under an HS map with Mitsuba 3 (render extra)"),
    ("build", "build", "build the ME HS dataset from bracketed scenes"),
    ("report", "report", "write the HTML report of a dataset or an evaluation"),
    ("train-baseline", "train_baseline", "fit the regression SSR baseline on a dataset"),
    ("evaluate", "evaluate", "score SSR models on a dataset (SAM, MRAE, RMSE, PSNR)"),
    ("train-ssr", "train_ssr", "train a network of the SSR zoo: the paper's, Mikamoto, Galliani, "
                               "HSCNN-D, AWAN, MST++ (torch extra)"),
    ("paper", "paper", "train every SSR method in both settings and write Tables 1-5"),
    ("demo", "demo", "run the whole pipeline on the simulated device"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mehs",
        description="High dynamic range hyperspectral capture, synthesis, datasets "
                    "and spectral super-resolution evaluation.")
    parser.add_argument("--version", action=_VersionAction,
                        help="print the versions of mehs, Python and its main libraries, and "
                             "which optional extras are installed, then exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module, help_ in COMMANDS:
        mod = importlib.import_module(f"mehs.cli.{module}")
        p = sub.add_parser(name, help=help_, description=help_)
        mod.configure(p)
        p.set_defaults(_run=mod.run)
    return parser


#: (extra, distributions it installs) in the order the README lists them.
EXTRAS: list[tuple[str, tuple[str, ...]]] = [
    ("test", ("pytest", "hypothesis")), ("onnx", ("onnxruntime", "onnx")),
    ("dask", ("dask", "distributed")), ("torch", ("torch",)), ("render", ("mitsuba",)),
    ("aravis", ("PyGObject",)), ("bench", ("colour-hdri", "psutil")),
]

#: Core dependencies whose versions a bug report needs.
CORE = ("numpy", "scipy", "numba", "OpenEXR", "opencv-contrib-python-headless",
        "colour-science", "spectral", "h5py", "matplotlib")


def versions_text() -> str:
    """mehs, Python and core library versions, and each extra: installed (its
    versions) or the command that installs it. Reads package metadata only (no import
    of torch or mitsuba), so it answers at once."""
    import platform
    from importlib import metadata

    def version(dist: str) -> str | None:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    core = ", ".join(f"{d} {version(d) or 'MISSING'}" for d in CORE)
    lines = [f"mehs {__version__}",
             f"Python {platform.python_version()} ({sys.executable})",
             f"core: {core}", "extras:"]
    for extra, dists in EXTRAS:
        got = [(d, version(d)) for d in dists]
        if all(v for _, v in got):
            lines.append(f"  {extra:7s} installed ({', '.join(f'{d} {v}' for d, v in got)})")
        else:
            # PyGObject builds against the system's GObject introspection (README)
            first = "the Debian packages in the README, then " if extra == "aravis" else ""
            lines.append(f'  {extra:7s} not installed: {first}python -m pip install -e ".[{extra}]"')
    return "\n".join(lines)


class _VersionAction(argparse.Action):
    """``--version``: :func:`versions_text`, computed only when asked for."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(versions_text())
        parser.exit()


#: Options whose value may start with '-' (``--times -1,5``): argparse would take the
#: value for an option and say only "expected one argument"; joined as ``--times=-1,5``
#: the command itself says what is wrong with it.
_DASH_VALUE_OPTIONS = ("--times",)


def _join_dash_values(argv: list[str]) -> list[str]:
    import re

    out: list[str] = []
    it = iter(range(len(argv)))
    for i in it:
        a = argv[i]
        if (a in _DASH_VALUE_OPTIONS and i + 1 < len(argv)
                and re.fullmatch(r"-[0-9.][0-9.,eE+\-\s]*", argv[i + 1])):
            out.append(f"{a}={argv[i + 1]}")
            next(it, None)
        else:
            out.append(a)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = [str(a) for a in (sys.argv[1:] if argv is None else argv)]
    args = parser.parse_args(_join_dash_values(argv))
    if not getattr(args, "_run", None):
        parser.print_help()
        return 1
    try:
        return int(args._run(args) or 0)
    except MehsError as exc:
        print(f"mehs: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        # the file system refused (not a directory, permission denied, disk
        # full, …): the user's path is at fault, so say which, without a traceback
        where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        what = exc.strerror or str(exc)
        print(f"mehs: error: {where}: {what}" if where else f"mehs: error: {what}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mehs: interrupted", file=sys.stderr)
        return 130


def progress_bars(off: bool = False) -> bool:
    """Whether a command draws progress bars: not when asked not to, nor into a log or a
    pipe, where every redraw of a bar is one more line of carriage returns."""
    return not off and sys.stderr.isatty()


def small_pages() -> bool:
    """Stop numpy from asking for transparent huge pages in this process; True if it did.

    numpy advises ``MADV_HUGEPAGE`` for every array of 4 MiB or more. Where the kernel
    then compacts memory to find 2 MiB pages on demand (``defrag = madvise``, common
    on virtual machines) the first touch of a large array stalls: a warm
    ``mehs fuse`` of a 512² scene spent 1.6–2.3 s of system time (2.1–3.0 s wall)
    with them, 0.7–0.9 s (1.5–1.8 s) without (issue 16). The command's arrays are
    allocated once and streamed through, so small pages cost no measurable
    compute. A ``NUMPY_MADVISE_HUGEPAGE`` set by the user wins; library use of mehs
    is not affected.

    The choice is also written to the environment (``NUMPY_MADVISE_HUGEPAGE=0``), which
    numpy reads at import: the worker processes of ``mehs build --workers N`` and of a
    Dask ``LocalCluster`` are new interpreters, and with huge pages advised again two
    workers built a 512² scene every 1.24–1.30 s instead of every 0.89 s.
    """
    import os

    if "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return False
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:                       # numpy < 2
        try:
            from numpy.core.multiarray import _set_madvise_hugepage
        except ImportError:                   # pragma: no cover - a numpy without it
            return False
    _set_madvise_hugepage(False)
    os.environ["NUMPY_MADVISE_HUGEPAGE"] = "0"        # for the processes this one starts
    return True


def reuse_heap() -> bool:
    """Let glibc reuse freed memory for later arrays instead of unmapping it; True if set.

    numpy's temporaries of a few MB (the linearity test makes ~40 of 7–14 MB) are
    each a fresh ``mmap`` under glibc's default thresholds, so every one is faulted in
    page by page again — on a VM where a first touch is expensive. With the mmap
    threshold at 256 MiB and the trim threshold at 512 MiB they come from the heap and
    reuse its pages: a warm 512² ``mehs fuse`` made half the page faults (155k → 80k),
    0.2 s less system time, median wall 1.39 → 1.23 s in 8 alternating runs, with a peak
    resident memory 1 % higher (680 → 687 MB). Used for ``mehs fuse`` only: the SSR
    commands' memory budget (:mod:`mehs.ssr.tiling`) models the default allocator.
    No-op (False) where the C library is not glibc.
    """
    from mehs._heap import set_thresholds

    return set_thresholds(256 << 20, 512 << 20)


def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` of the ``mehs`` command: ``mehs: warning: MESSAGE``.

    mehs's own warnings (and plain ``UserWarning``, whose messages name their file) are
    shown as their message; another library's keep their category's name, which says
    where they come from. Set by :func:`console` only: tests and scripts calling
    :func:`main` keep Python's own display and ``pytest.warns``.
    """
    name = getattr(category, "__name__", "Warning")
    own = category is UserWarning or getattr(category, "__module__", "").startswith("mehs")
    text = str(message) if own else f"{name}: {message}"
    stream = file if file is not None else sys.stderr
    try:
        print(f"mehs: warning: {text}", file=stream)
    except (OSError, ValueError):  # a closed or broken stderr: nothing to show it on
        pass


def console() -> None:
    """The ``mehs`` command (and ``python -m mehs``): :func:`main`, then a quick exit.

    Runs with small pages (:func:`small_pages`); ``mehs fuse`` also with the C heap
    reused (:func:`reuse_heap`).

    Interpreter teardown re-scans every object still alive with the cyclic garbage
    collector, several times; after numba has loaded a kernel (or torch a model)
    that took 0.25–0.35 s of every ``mehs fuse`` (issue 16). One collection here
    still finalises whatever is garbage; freezing the survivors then lets the
    teardown skip them (they are freed with the process). Not done in
    :func:`main`, which tests and scripts call in a process that goes on.
    """
    small_pages()
    if sys.argv[1:2] == ["fuse"]:
        reuse_heap()
    import warnings

    # a warning is one line for the user, not a Python source location and its code line
    warnings.showwarning = show_warning
    code = main()
    import gc

    gc.collect()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    console()
