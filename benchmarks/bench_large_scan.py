"""Real line-scan cameras' sizes through ``mehs fuse`` and ``mehs resample``: peak memory and time.

    python benchmarks/bench_large_scan.py [--lines 500,1000,2000] [--samples 1024] [--bands 224]
                                          [--keep DIR]

A Specim FX10 gives 1024 spatial samples × 224 bands (400–1000 nm) per line and scans
thousands of lines on a stage. For each ``--lines`` L this writes a bracket of three
Specim-layout folders (uint16 BIL ENVI, 12-bit, ``tint`` in the header, a per-exposure
dark reference of 8 lines; exposures 1, 8 and 64 ms) of a synthetic HDR scene (smooth
reflectance spectra × a daylight-like illuminant, shading, lamp stripes ~300× brighter;
photon noise, read noise, dark current, column fixed pattern, clipping at 4095), then
runs, each in a fresh child process whose peak RSS comes from ``os.wait4``:

- reference: a plain numpy read of the stack (``np.fromfile`` of the three raw files);
- ``mehs fuse`` of the three folders;
- ``mehs resample`` of the fused radiance to 31 bands (400–700 nm).

and prints size, wall seconds, peak RSS and RSS / stack bytes. The design target: merge
peak ≤ 2× the stack, and ``mehs fuse`` bounded so a 24 GiB machine fuses a 5000-line FX10
scan (a 6.9 GB stack).

:func:`write_scan_bracket` is also used by the tests (``tests/test_h22_scale_*.py``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: Exposure times (ms) of the bracket, ×8 apart.
TIMES_MS = (1.0, 8.0, 64.0)


def _fmt_list(values) -> str:
    return "{" + ", ".join(f"{v:.10g}" for v in values) + "}"


def write_envi_u16(hdr: Path, data_lines, *, lines: int, samples: int, bands: int,
                   wavelengths, fwhm, tint_ms: float, units: str = "Nanometers") -> None:
    """Write a uint16 BIL ENVI pair (``hdr`` + ``.raw``) line chunk by line chunk.

    ``data_lines`` yields uint16 arrays ``(n, samples, bands)`` summing to ``lines``.
    """
    hdr.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    with open(hdr.with_suffix(".raw"), "wb") as fh:
        for chunk in data_lines:
            np.ascontiguousarray(chunk.transpose(0, 2, 1), dtype="<u2").tofile(fh)
            n += chunk.shape[0]
    assert n == lines, (n, lines)
    hdr.write_text(
        "ENVI\ndescription = {mehs bench_large_scan synthetic line scan}\n"
        f"samples = {samples}\nlines = {lines}\nbands = {bands}\nheader offset = 0\n"
        "file type = ENVI Standard\ndata type = 12\ninterleave = bil\nbyte order = 0\n"
        f"tint = {tint_ms:g}\nwavelength units = {units}\n"
        f"wavelength = {_fmt_list(wavelengths)}\nfwhm = {_fmt_list(fwhm)}\n",
        encoding="ascii")


def scene_radiance(l0: int, l1: int, samples: int, wl_nm: np.ndarray, seed: int) -> np.ndarray:
    """float32 ``(l1 − l0, samples, bands)`` photo-electrons per ms of a synthetic HDR scene.

    Deterministic per line (the same lines whatever the chunking): 12 smooth
    reflectance spectra in patches 48 lines × 96 samples, a daylight-like
    illuminant (a 5800 K Planck curve), a per-band quantum efficiency, a shading
    ramp over the samples and lamp stripes (every 160th line, 8 lines long,
    samples 300–340) ~300× brighter than a white patch.
    """
    rng = np.random.default_rng(seed)
    x = (wl_nm - wl_nm.min()) / max(1e-9, np.ptp(wl_nm))
    k = 12
    # smooth reflectances: sigmoids and bumps between 0.03 and 0.9
    c = rng.uniform(0.0, 1.0, k)[:, None]
    w = rng.uniform(0.08, 0.4, k)[:, None]
    lo = rng.uniform(0.03, 0.3, k)[:, None]
    hi = rng.uniform(0.4, 0.9, k)[:, None]
    refl = lo + (hi - lo) / (1 + np.exp(-(x[None, :] - c) / w))
    lam = wl_nm * 1e-9
    planck = 1 / (lam ** 5 * (np.exp(1.4388e-2 / (lam * 5800.0)) - 1))
    planck /= planck.max()
    qe = 0.25 + 0.75 * np.exp(-0.5 * ((wl_nm - 650.0) / 180.0) ** 2)
    spectra = (refl * (planck * qe)[None, :] * 30.0).astype(np.float32)     # e-/ms, white ~30
    lamp = (planck * qe * 9000.0).astype(np.float32)
    lines = np.arange(l0, l1)
    s = np.arange(samples)
    idx = ((lines[:, None] // 48) * 7 + (s[None, :] // 96) * 3) % k
    shade = (0.35 + 0.65 * (s / max(1, samples - 1)) ** 0.7).astype(np.float32)
    out = spectra[idx] * shade[None, :, None]
    is_lamp = ((lines % 160) < 8)[:, None] & ((s >= 300) & (s < 340))[None, :]
    out[is_lamp] = lamp
    return out


def sensor_dn(e_per_ms: np.ndarray, t_ms: float, rng: np.random.Generator, *,
              gain: float = 0.5, read_e: float = 6.0, dark_e_per_ms: float = 2.0,
              offset: np.ndarray | float = 64.0, poisson: bool = False) -> np.ndarray:
    """12-bit uint16 DN of ``e_per_ms`` (electrons/ms) exposed ``t_ms``: shot noise (Poisson,
    or its normal approximation when ``poisson`` is false — ~5× faster), read noise,
    dark current, an offset (scalar or per column/band), clipping at 4095."""
    e = e_per_ms * np.float32(t_ms) + np.float32(dark_e_per_ms * t_ms)
    if poisson:
        e = rng.poisson(e).astype(np.float32)
    else:
        e = e + np.sqrt(e) * rng.standard_normal(e.shape, dtype=np.float32)
    e += rng.standard_normal(e.shape, dtype=np.float32) * np.float32(read_e)
    dn = e * np.float32(gain) + offset
    return np.clip(np.rint(dn), 0, 4095).astype(np.uint16)


def write_scan_bracket(root: str | Path, lines: int, samples: int = 1024, bands: int = 224,
                       wl_range=(400.0, 1000.0), *, times_ms=TIMES_MS, seed: int = 1,
                       chunk: int = 64, poisson: bool = False, dark_lines: int = 8,
                       wavelengths=None, units: str = "Nanometers") -> list[Path]:
    """Write a bracket of Specim-layout folders ``root/e<k>`` (one per exposure); return them.

    ``wavelengths`` (nm, any order) overrides ``wl_range``; they are written as
    given, divided by 1000 when ``units`` is ``"Micrometers"``.
    """
    root = Path(root)
    if wavelengths is None:
        wl = np.linspace(wl_range[0], wl_range[1], bands)
    else:
        wl = np.asarray(wavelengths, dtype=np.float64)
        bands = wl.size
    step = np.abs(np.diff(np.sort(wl))).mean() if wl.size > 1 else 10.0
    fwhm = np.full(bands, 1.5 * step)
    div = 1000.0 if units.lower().startswith("micro") else 1.0
    rng0 = np.random.default_rng(seed + 1000)
    col_offset = (64.0 + rng0.normal(0, 2.0, (samples, 1))).astype(np.float32)   # column FPN
    order = np.argsort(wl)
    folders = []
    for k, t in enumerate(times_ms):
        folder = root / f"e{k}"
        cid = f"scan{k}"
        rng = np.random.default_rng([seed, k])

        def gen(t=t, rng=rng):
            for l0 in range(0, lines, chunk):
                l1 = min(lines, l0 + chunk)
                rad_sorted = scene_radiance(l0, l1, samples, wl[order], seed)
                rad = np.empty_like(rad_sorted)
                rad[:, :, order] = rad_sorted
                yield sensor_dn(rad, t, rng, offset=col_offset, poisson=poisson)

        def dark(t=t, rng=rng):
            yield sensor_dn(np.zeros((dark_lines, samples, bands), np.float32), t, rng,
                            offset=col_offset, poisson=poisson)

        kw = dict(samples=samples, bands=bands, wavelengths=wl / div, fwhm=fwhm / div,
                  tint_ms=t, units=units)
        write_envi_u16(folder / "capture" / f"{cid}.hdr", gen(), lines=lines, **kw)
        write_envi_u16(folder / "capture" / f"DARKREF_{cid}.hdr", dark(), lines=dark_lines, **kw)
        folders.append(folder)
    return folders


# ------------------------------------------------------------------------ measuring

def _run_child(cmd: list[str], env: dict) -> tuple[float, int, int, str]:
    """(wall s, peak RSS bytes, return code, stderr tail) of ``cmd`` in a fresh process."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = p.stderr.read().decode(errors="replace")
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    return wall, ru.ru_maxrss * 1024, p.returncode, err[-2000:]


_READ_STACK = ("import sys, numpy as np\n"
               "a = [np.fromfile(f, dtype='<u2') for f in sys.argv[1:]]\n"
               "print(sum(x.nbytes for x in a))\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lines", default="500,1000,2000")
    ap.add_argument("--samples", type=int, default=1024)
    ap.add_argument("--bands", type=int, default=224)
    ap.add_argument("--method", default="poisson")
    ap.add_argument("--keep", default=None, help="folder to keep (and reuse) the brackets")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    from _load import load_line

    tmp = Path(tempfile.mkdtemp(prefix="mehs_bench_large_"))
    root = Path(args.keep) if args.keep else tmp / "brackets"
    env = dict(os.environ, PYTHONPATH=str(HERE.parent))
    mehs = [sys.executable, "-m", "mehs"]
    rows = []
    try:
        for L in [int(v) for v in args.lines.split(",")]:
            b = root / f"fx_{L}x{args.samples}x{args.bands}"
            t0 = time.perf_counter()
            if not (b / "e2" / "capture" / "scan2.hdr").exists():
                shutil.rmtree(b, ignore_errors=True)
                write_scan_bracket(b, L, args.samples, args.bands)
            folders = [b / f"e{k}" for k in range(len(TIMES_MS))]
            raws = [str(f / "capture" / f"scan{k}.raw") for k, f in enumerate(folders)]
            stack = sum(os.path.getsize(r) for r in raws)
            print(f"{L} lines: bracket ready in {time.perf_counter() - t0:.0f} s "
                  f"(stack {stack / 2**20:.0f} MiB); {load_line()}", flush=True)
            out = tmp / f"fused_{L}"
            runs = [("numpy read of the stack (reference)",
                     [sys.executable, "-c", _READ_STACK, *raws]),
                    ("mehs fuse", [*mehs, "fuse", *map(str, folders), "--out", str(out),
                                   "--method", args.method, "--verify", "none"]),
                    ("mehs resample → 31 bands",
                     [*mehs, "resample", str(out / "radiance.hdr"), str(tmp / f"hs31_{L}.hdr")])]
            for what, cmd in runs:
                wall, rss, rc, err = _run_child(cmd, env)
                if rc:
                    print(f"  {what} failed ({rc}):\n{err}")
                rows.append((L, what, wall, rss, stack, rc))
                print(f"  {what:<38} {wall:7.1f} s  {rss / 2**20:8.0f} MiB  "
                      f"{rss / stack:5.2f}× stack", flush=True)
            shutil.rmtree(out, ignore_errors=True)
            for f in tmp.glob(f"hs31_{L}.*"):
                f.unlink()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\n{'lines × samples × bands':<24} {'stack MiB':>9}  {'run':<38} {'wall s':>7} "
          f"{'peak RSS MiB':>12} {'RSS/stack':>9}")
    for L, what, wall, rss, stack, rc in rows:
        print(f"{f'{L} × {args.samples} × {args.bands}':<24} {stack / 2**20:9.0f}  {what:<38} "
              f"{wall:7.1f} {rss / 2**20:12.0f} {rss / stack:8.2f}×" + ("" if rc == 0 else "  FAILED"))
    print("after:", load_line())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
