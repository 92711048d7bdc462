"""Compiling the stored kernels in a child process, and the vector width they use.

:mod:`mehs.synthesis._native` keeps the one-pass kernels' machine code. numba compiles
for the CPU it runs on with LLVM's tuning of that CPU, and LLVM tunes Intel's AVX-512
cores (Skylake-SP through Sapphire Rapids, the client cores since Ice Lake) to prefer
256-bit vectors: mixed code on them loses clock speed in 512-bit instructions. The merge
kernels are long runs of float arithmetic over 16 samples, bound by the vector units
(docs/performance.md): on such a core (LLVM's ``rocketlake`` / ``sapphirerapids``,
2026-12-06) 512-bit vectors made the default merge 15–18 % faster and the radiance-only
one 18–23 % (``benchmarks/RESULTS.md``, "Issue 16, session 30"); AMD's Zen 4 gets them
by default. The width does not change a number: without ``fastmath`` LLVM vectorises
each sample's arithmetic as written, so the stored kernel gives numba's bits either way
(tested).

numba takes the width from its CPU features (``NUMBA_CPU_FEATURES``), read once per
process for all its code, so the stored kernels are compiled in a child process given
those features: the parent's numba and a user's own numba code keep LLVM's choice.
``MEHS_KERNEL_VECTORS=256`` keeps LLVM's choice for the stored kernels too; a user's own
``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES`` is left as it is.

A child also compiles every kernel of more than :data:`DEFAULT_TUNED_EXPOSURES`
exposures, with the LLVM options of :func:`llvm_options` (process-wide settings of
LLVM, so not in the parent either).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def tuning() -> str:
    """The LLVM features the stored kernels add to the host's ('' for none)."""
    if os.environ.get("MEHS_KERNEL_VECTORS", "").strip() == "256":
        return ""
    if os.environ.get("NUMBA_CPU_NAME") or os.environ.get("NUMBA_CPU_FEATURES"):
        return ""           # the user chose numba's target: compiled in-process, for it
    import llvmlite.binding as ll

    return "-prefer-256-bit" if ll.get_host_cpu_features().get("avx512f") else ""


#: Exposures up to which LLVM's default tuning vectorises every one-pass merge kernel
#: (numba's own build: the per-band Poisson, Robertson and inverse-variance ones up to 5,
#: Debevec's and the binned ones up to 3, none from 6).
DEFAULT_TUNED_EXPOSURES = 3


def llvm_options(P: int) -> tuple[str, ...]:
    """The LLVM options a stored kernel of ``P`` exposures is compiled with (none for 3 or
    fewer).

    The one-pass merges vectorise their sample loop with each sample's state in
    registers, which needs the exposure loop inside it unrolled: ``P`` is a compile-time
    constant, and numba indexes the tuple of exposures by the loop variable through a
    ``switch`` that only unrolling removes. LLVM's full-unroll threshold (300 at
    ``-O3``) left that loop rolled in Debevec's and the binned kernels from 4 exposures
    and in every kernel from 6, whose sample loops then stayed scalar: 8.5–13× the time
    per exposure of a 3-exposure bracket (``benchmarks/RESULTS.md``, "Issue 16, session
    36"). Unrolled, the sample loop's run-time alias checks (arrays stored × arrays read,
    growing with ``P``) pass LLVM's cap of 128 ("too many memory checks needed"); one
    check per loop entry, a few hundred compares for 16 exposures against a row's
    hundreds of samples. Both limits are raised, enough for every merge kernel up to
    16 exposures (tested on the kernels' code: ``set_option`` ignores an option LLVM
    does not know, so a renamed one would leave them scalar silently). The numbers stay
    the same: without ``fastmath`` each vector lane computes what the scalar loop does
    (tested to the bit).
    """
    if P <= DEFAULT_TUNED_EXPOSURES:
        return ()
    return ("-unroll-threshold=4000", "-vectorize-memory-check-threshold=4096")


def apply_llvm_options(options) -> None:
    """Set LLVM's command-line ``options`` for this whole process (a child's)."""
    if options:
        import llvmlite.binding as ll

        for option in options:
            ll.set_option("mehs", option)


def start(kind: str, dtype_name: str, P: int, marker: Path, key: dict, *,
          background: bool) -> subprocess.Popen:
    """Start a child process that compiles and stores one entry point.

    It stores the entry under ``key`` (the parent's: the child's own environment
    differs by the features it is given), if its own sources still give that key, and
    holds ``marker``'s lock while compiling. A ``background`` child runs at a lower
    priority and leaves when another child holds the lock; otherwise it waits for that
    child and loads what it stored. Raises ``OSError`` if the process cannot start.
    """
    # the working folder off the import path first (``-c`` puts it first: a json.py or
    # numpy/ there ran in the child); mehs's own folder last, behind the standard
    # library; no os.nice on Windows
    code = ("import os, sys; sys.path[:] = [p for p in sys.path if p not in ('', '.')] "
            "+ [sys.argv[4]]; import json; "
            "getattr(os, 'nice', abs)(10) if sys.argv[7] == '1' else None; "
            "import numpy as np; from mehs.synthesis import _native; "
            "_native._child_build(sys.argv[1], np.dtype(sys.argv[2]), int(sys.argv[3]), "
            "sys.argv[5], json.loads(sys.argv[6]), wait=sys.argv[7] == '0')")
    if not sys.executable:          # an embedding application: no interpreter to start
        raise OSError("no Python executable to start a child process with")
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    extra = key.get("tuning", "")
    if extra:
        import llvmlite.binding as ll

        env["NUMBA_CPU_FEATURES"] = ll.get_host_cpu_features().flatten() + "," + extra
    # a working folder deleted under the parent: Python 3.13 then failed to import numpy
    # in the child ("SystemError: error return without exception set") even with the
    # folder off sys.path; relative paths mean nothing there, so the child starts in
    # mehs's own folder instead
    try:
        os.getcwd()
        cwd = None
    except OSError:
        cwd = root
    return subprocess.Popen(
        [sys.executable, "-c", code, kind, dtype_name, str(P), root, str(marker),
         json.dumps(key), "1" if background else "0"],
        env=env, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)


def locked_elsewhere(marker: Path) -> bool:
    """Whether a process holds ``marker``'s lock (a child compiling its entry)."""
    try:
        import fcntl
        fd = os.open(marker, os.O_RDONLY)
    except (ImportError, OSError):
        return False        # not POSIX, or no child ever started
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)        # (releases the probe's own lock)
    return False
