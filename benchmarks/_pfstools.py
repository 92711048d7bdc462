"""pfstools' ``pfshdrcalibrate`` as a merge reference for ``bench_synthesis.py`` (issue 16).

pfstools (Debian package ``pfstools``, 2.2) merges a bracket with the noise-aware estimator
of Hanji, Zhong & Mantiuk (2020) when given a linear response (``-r linear -c none``). It
reads and writes *PFS streams*: frames of float32 ``X``, ``Y``, ``Z`` channels (CIE XYZ of
linear sRGB, D65) with text tags; each frame of a bracket carries its exposure as the APEX
brightness value ``BV``. Like OpenCV it merges three channels at a time, so a 204-band
bracket goes through it as 68 three-band images, one ``pfshdrcalibrate`` process each (it
is single-threaded: the benchmark runs as many processes at once as it gives threads to
numba and OpenCV).

The stream layout is that of ``pfs::DOMIO::writeFrame`` (``pfs_format_spec.pdf`` in the
package): ``PFS1``, width and height, channel count, frame tags, then per channel its
name and tags, ``ENDH``, and the channels' float32 data in that order, rows first.

References
----------
Hanji, P., Zhong, F., & Mantiuk, R. K. (2020). Noise-aware merging of high dynamic range
image stacks without camera calibration. ECCV 2020 Workshops (AIM).
"""

from __future__ import annotations

import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor

import numpy as np

#: linear sRGB (D65) → XYZ, as pfstools converts (``pfs::transformColorSpace``); it turns
#: the channels back to RGB before merging, so three bands pass through unchanged but for
#: float rounding (about 1e-6 relative)
RGB_TO_XYZ = np.array([[0.412424, 0.357579, 0.180464],
                       [0.212656, 0.715158, 0.072186],
                       [0.019332, 0.119193, 0.950444]])
XYZ_TO_RGB = np.linalg.inv(RGB_TO_XYZ)
#: pfstools' APEX speed value of ISO 100 (``Sv = log2(ISO / 3.125)``, as ``pfsinhdrgen``)
_SV_ISO100 = float(np.log2(100 / 3.125))


def available() -> bool:
    return shutil.which("pfshdrcalibrate") is not None


def version() -> str:
    """The installed package's version (dpkg), or '' where unknown."""
    try:
        out = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "pfstools"],
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


def frame_bytes(rgb: np.ndarray, tags: dict[str, str]) -> bytes:
    """One PFS frame of a ``(rows, cols, 3)`` linear-RGB image."""
    h, w, c = rgb.shape
    if c != 3:
        raise ValueError(f"a PFS colour frame takes 3 channels, got {c}")
    xyz = np.asarray(rgb, np.float32) @ RGB_TO_XYZ.T.astype(np.float32)
    head = [b"PFS1", b"%d %d" % (w, h), b"3", b"%d" % len(tags)]
    head += [f"{k}={v}".encode() for k, v in tags.items()]
    for name in (b"X", b"Y", b"Z"):
        head += [name, b"0"]
    body = b"".join(np.ascontiguousarray(xyz[:, :, k], dtype="<f4").tobytes() for k in range(3))
    return b"\n".join(head) + b"\nENDH" + body


def read_rgb(stream: bytes, source: str = "pfshdrcalibrate") -> np.ndarray:
    """The first frame of a PFS stream as a ``(rows, cols, 3)`` float32 linear-RGB image."""
    pos = 0

    def line() -> str:
        nonlocal pos
        end = stream.find(b"\n", pos)
        if end < 0:
            raise ValueError(f"{source}: truncated PFS header")
        text = stream[pos:end].decode("ascii")
        pos = end + 1
        return text

    if line() != "PFS1":
        raise ValueError(f"{source}: not a PFS stream")
    w, h = (int(v) for v in line().split())
    nch = int(line())
    for _ in range(int(line())):
        line()
    names = []
    for _ in range(nch):
        names.append(line())
        for _ in range(int(line())):
            line()
    if stream[pos:pos + 4] != b"ENDH":
        raise ValueError(f"{source}: PFS header does not end in ENDH")
    pos += 4
    need = 4 * w * h * nch
    if len(stream) - pos < need:
        raise ValueError(f"{source}: PFS stream holds {len(stream) - pos} data bytes, "
                         f"its header says {need}")
    data = np.frombuffer(stream, "<f4", w * h * nch, pos).reshape(nch, h, w)
    ch = dict(zip(names, data))
    if not {"X", "Y", "Z"} <= ch.keys():
        raise ValueError(f"{source}: PFS frame without X, Y, Z channels ({names})")
    xyz = np.stack([ch["X"], ch["Y"], ch["Z"]], axis=-1).astype(np.float64)
    return (xyz @ XYZ_TO_RGB.T).astype(np.float32)


def bracket_stream(images: list[np.ndarray], times: np.ndarray, dark: np.ndarray,
                   bit_depth: int) -> bytes:
    """The PFS stream of one three-band bracket: each exposure dark-subtracted and scaled
    to 0..1 of the sensor's range (pfstools scales back by ``2**bpp − 1``), tagged with
    its APEX brightness value (aperture 1, ISO 100)."""
    full = float(2 ** bit_depth - 1)
    frames = []
    for img, t in zip(images, times):
        rgb = (img.astype(np.float32) - dark) / np.float32(full)
        bv = float(np.log2(1.0 / t)) - _SV_ISO100
        frames.append(frame_bytes(rgb, {"BV": repr(bv), "ISO": "100", "aperture": "1",
                                        "exposure_time": repr(float(t)),
                                        "LUMINANCE": "RELATIVE"}))
    return b"".join(frames)


def saturation_offset(saturation: float, dark_max: float, bit_depth: int) -> float:
    """pfstools' ``--saturation-offset`` for a raw saturation level and dark level.

    It calls a value saturated above ``(1 − offset)·(2**bpp − 1)`` of the stream's values;
    the streams here are dark-subtracted, so its default offset (1 %) would sit above the
    largest value a clipped pixel reaches (``2**bpp − 1 − dark``) and count saturated
    samples as valid (bright pixels then came out 40–70 % low).
    """
    full = float(2 ** bit_depth - 1)
    return 1.0 - (float(saturation) - float(dark_max)) / full


def merge_stream(stream: bytes, bit_depth: int, offset: float) -> bytes:
    """Run ``pfshdrcalibrate`` (linear response, no self-calibration) on one stream."""
    p = subprocess.run(["pfshdrcalibrate", "-r", "linear", "-c", "none", "-b", str(bit_depth),
                        "-o", repr(offset)], input=stream, capture_output=True)
    if p.returncode != 0:
        raise RuntimeError("pfshdrcalibrate failed: " + p.stderr.decode(errors="replace")[-400:])
    return p.stdout


def merge_all(streams: list[bytes], bit_depth: int, offset: float, workers: int) -> list[bytes]:
    """Every stream through its own process, ``workers`` at a time."""
    with ThreadPoolExecutor(max(1, workers)) as pool:
        return list(pool.map(lambda s: merge_stream(s, bit_depth, offset), streams))
