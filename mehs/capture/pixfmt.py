"""GenICam pixel formats of monochrome (hyperspectral) frames: PFNC codes, packing, unpacking.

A line-scan hyperspectral camera sends one spectral frame per scan line,
``Height`` = bands rows × ``Width`` = spatial samples columns, in one of the
monochrome formats below. Codes are the 32-bit GenICam PFNC values (bits
16–23 = bits per pixel) that GigE Vision / USB3 Vision leaders carry.

Packed 12-bit layouts (two pixels ``p0``, ``p1`` in three bytes ``b0 b1 b2``):

- ``Mono12Packed`` (GigE Vision 1.x): ``b0 = p0[11:4]``,
  ``b1 = p1[3:0] << 4 | p0[3:0]``, ``b2 = p1[11:4]``;
- ``Mono12p`` (PFNC, USB3 Vision and GigE Vision 2): the little-endian bit
  stream ``b0 = p0[7:0]``, ``b1 = p1[3:0] << 4 | p0[11:8]``, ``b2 = p1[11:4]``.

References
----------
EMVA, *GenICam Pixel Format Naming Convention (PFNC) 2.4*, 2022, §5 (Mono12p)
and Appendix (GigE Vision legacy Mono12Packed).
AIA, *GigE Vision 2.0*, 2011, §28 "Pixel formats".
"""

from __future__ import annotations

import numpy as np

#: PFNC codes (GigE Vision / USB3 Vision) of the formats mehs reads.
PIXEL_FORMATS: dict[str, int] = {
    "Mono8": 0x01080001,
    "Mono10": 0x01100003,
    "Mono12": 0x01100005,
    "Mono12Packed": 0x010C0006,
    "Mono12p": 0x010C0047,
    "Mono14": 0x01100025,
    "Mono16": 0x01100007,
}
_BY_CODE = {v: k for k, v in PIXEL_FORMATS.items()}

#: Significant bits per format (Mono16 frames of a 12-bit sensor still hold 12 significant bits).
SIGNIFICANT_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono12Packed": 12, "Mono12p": 12,
                    "Mono14": 14, "Mono16": 16}

#: Formats a 12-bit (or deeper) hyperspectral capture can use, in order of preference:
#: unpacked first (no CPU unpacking), packed next (¾ of the bandwidth).
PREFERRED = ("Mono12", "Mono16", "Mono14", "Mono12p", "Mono12Packed", "Mono10")


def name_of(code: int) -> str:
    """PFNC name of ``code`` (``'0x…'`` when unknown)."""
    return _BY_CODE.get(int(code), f"0x{int(code):08X}")


def bits_per_pixel(code: int) -> int:
    """Bits each pixel occupies in a buffer (PFNC bits 16–23)."""
    return (int(code) >> 16) & 0xFF


def frame_bytes(code: int, width: int, height: int) -> int:
    """Bytes of one ``width × height`` frame in format ``code``."""
    return (int(width) * int(height) * bits_per_pixel(code) + 7) // 8


def _unpack12(raw: np.ndarray, n: int, layout: str) -> np.ndarray:
    # an odd pixel count ends mid-triple (12·n bits round up to whole bytes)
    b = np.zeros(3 * ((n + 1) // 2), dtype=np.uint16)
    b[:raw.size] = raw
    b = b.reshape(-1, 3)
    out = np.empty((b.shape[0], 2), dtype=np.uint16)
    if layout == "Mono12Packed":
        out[:, 0] = (b[:, 0] << 4) | (b[:, 1] & 0x0F)
        out[:, 1] = (b[:, 2] << 4) | (b[:, 1] >> 4)
    else:  # Mono12p
        out[:, 0] = b[:, 0] | ((b[:, 1] & 0x0F) << 8)
        out[:, 1] = (b[:, 1] >> 4) | (b[:, 2] << 4)
    return out.reshape(-1)[:n]


def unpack(data: bytes | memoryview | np.ndarray, code: int, width: int, height: int) -> np.ndarray:
    """Frame bytes → uint16 ``(height, width)`` pixel values.

    Parameters
    ----------
    data
        Exactly :func:`frame_bytes` bytes (little-endian for multi-byte formats).
    code
        PFNC pixel format code.

    Raises
    ------
    ValueError
        Unknown format or a byte count that does not match ``width × height``.
    """
    name = name_of(code)
    if name not in PIXEL_FORMATS:
        raise ValueError(f"pixel format {name} is not a monochrome format mehs reads "
                         f"({', '.join(PIXEL_FORMATS)})")
    raw = np.frombuffer(data, dtype=np.uint8)
    need = frame_bytes(code, width, height)
    if raw.size != need:
        raise ValueError(f"{name} frame of {width}×{height} needs {need} bytes, got {raw.size}")
    n = int(width) * int(height)
    if name == "Mono8":
        px = raw.astype(np.uint16)
    elif name in ("Mono12Packed", "Mono12p"):
        px = _unpack12(raw, n, name)
    else:
        px = raw.view("<u2").astype(np.uint16)
    return px.reshape(int(height), int(width))


def pack(pixels: np.ndarray, code: int) -> bytes:
    """uint16 pixels (any shape, C order) → frame bytes in format ``code`` (inverse of :func:`unpack`)."""
    name = name_of(code)
    px = np.ascontiguousarray(pixels, dtype=np.uint16).reshape(-1)
    n = px.size
    if name not in PIXEL_FORMATS:
        raise ValueError(f"cannot pack pixel format {name}")
    if int(px.max(initial=0)) >> SIGNIFICANT_BITS[name]:
        raise ValueError(f"{name}: pixel values exceed {SIGNIFICANT_BITS[name]} bits")
    if name == "Mono8":
        return px.astype(np.uint8).tobytes()
    if name in ("Mono12Packed", "Mono12p"):
        if px.size % 2:
            px = np.append(px, np.uint16(0))
        p = px.reshape(-1, 2)
        out = np.empty((p.shape[0], 3), dtype=np.uint8)
        if name == "Mono12Packed":
            out[:, 0] = p[:, 0] >> 4
            out[:, 1] = ((p[:, 1] & 0x0F) << 4) | (p[:, 0] & 0x0F)
            out[:, 2] = p[:, 1] >> 4
        else:
            out[:, 0] = p[:, 0] & 0xFF
            out[:, 1] = ((p[:, 1] & 0x0F) << 4) | (p[:, 0] >> 8)
            out[:, 2] = p[:, 1] >> 4
        return out.tobytes()[:frame_bytes(code, n, 1)]
    return px.astype("<u2").tobytes()
