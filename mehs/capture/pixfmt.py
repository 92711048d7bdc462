"""GenICam pixel formats of monochrome (hyperspectral) frames: PFNC codes, packing, unpacking.

A line-scan hyperspectral camera sends one spectral frame per scan line,
``Height`` = bands rows × ``Width`` = spatial samples columns, in one of the
monochrome formats below. Codes are the 32-bit GenICam PFNC values (bits
16–23 = bits per pixel) that GigE Vision / USB3 Vision leaders carry.

Packed layouts (``b0 b1 …`` the bytes in buffer order, ``p[m:l]`` bits m…l of a pixel):

- PFNC ``Mono10p`` / ``Mono12p`` / ``Mono14p`` (USB3 Vision, GigE Vision 2): a
  little-endian bit stream, pixel ``i`` in stream bits ``i·N … i·N+N−1`` and byte
  ``k`` holding stream bits ``8k … 8k+7``; e.g. Mono12p ``b0 = p0[7:0]``,
  ``b1 = p1[3:0] << 4 | p0[11:8]``, ``b2 = p1[11:4]``, Mono10p
  ``b0 = p0[7:0]``, ``b1 = p1[5:0] << 2 | p0[9:8]``, …, ``b4 = p3[9:2]``;
- GigE Vision 1.x "grouped" ``Mono12Packed`` / ``Mono10Packed`` (two pixels in three
  bytes, MSBs first): ``b0 = p0[N−1:N−8]``, ``b1 = p1[low] << 4 | p0[low]`` (the
  ``N−8`` low bits of each), ``b2 = p1[N−1:N−8]``.

A frame is one stream: lines are not padded, so a line of odd width ends mid-group
(GigE Vision 2.0 §28: "the first pixel of the second line will not start on a 3-byte
boundary"). Unpacked formats of more than 8 bits (Mono10/12/14/16) are little-endian
16-bit words, LSB-aligned (PFNC; GigE Vision sends pixel data little-endian,
unlike its big-endian control registers).

References
----------
EMVA, *GenICam Pixel Format Naming Convention (PFNC) 2.4*, 2022, §5 (Mono10p,
Mono12p, Mono14p, Figures "lsb packing") and Appendix (GigE Vision legacy
Mono10Packed / Mono12Packed).
AIA, *GigE Vision 2.0*, 2011, §28 "Pixel formats".
"""

from __future__ import annotations

import numpy as np

#: PFNC codes (GigE Vision / USB3 Vision) of the formats mehs reads.
PIXEL_FORMATS: dict[str, int] = {
    "Mono8": 0x01080001,
    "Mono10": 0x01100003,
    "Mono10Packed": 0x010C0004,
    "Mono10p": 0x010A0046,
    "Mono12": 0x01100005,
    "Mono12Packed": 0x010C0006,
    "Mono12p": 0x010C0047,
    "Mono14": 0x01100025,
    "Mono14p": 0x010E0104,
    "Mono16": 0x01100007,
}
_BY_CODE = {v: k for k, v in PIXEL_FORMATS.items()}

#: Significant bits per format (Mono16 frames of a 12-bit sensor still hold 12 significant bits).
SIGNIFICANT_BITS = {"Mono8": 8, "Mono10": 10, "Mono10Packed": 10, "Mono10p": 10, "Mono12": 12,
                    "Mono12Packed": 12, "Mono12p": 12, "Mono14": 14, "Mono14p": 14, "Mono16": 16}

#: Bit-stream packed (PFNC "p") and GigE Vision grouped (two pixels in three bytes) formats.
_LSB_STREAM = ("Mono10p", "Mono12p", "Mono14p")
_GROUPED = ("Mono10Packed", "Mono12Packed")

#: Formats a hyperspectral capture can use, in order of preference when the camera's current
#: one is unusable (Mono8): deeper first — a camera offering Mono14 has a ≥ 14-bit pipeline, and
#: picking Mono12 there would drop two bits of dynamic range —, at equal depth unpacked (no CPU
#: unpacking) before packed; Mono12 before Mono16, whose content on a 12-bit sensor may be
#: MSB-aligned (``PixelDynamicRangeMax`` tells, when the camera has it).
PREFERRED = ("Mono14", "Mono12", "Mono16", "Mono14p", "Mono12p", "Mono12Packed",
             "Mono10", "Mono10p", "Mono10Packed")


def name_of(code: int) -> str:
    """PFNC name of ``code`` (``'0x…'`` when unknown)."""
    return _BY_CODE.get(int(code), f"0x{int(code):08X}")


def bits_per_pixel(code: int) -> int:
    """Bits each pixel occupies in a buffer (PFNC bits 16–23)."""
    return (int(code) >> 16) & 0xFF


def frame_bytes(code: int, width: int, height: int) -> int:
    """Bytes of one ``width × height`` frame in format ``code``."""
    return (int(width) * int(height) * bits_per_pixel(code) + 7) // 8


def _unpack_lsb_stream(raw: np.ndarray, n: int, bits: int) -> np.ndarray:
    """PFNC "p" formats: pixel ``i`` = stream bits ``i·bits …``; byte ``k`` = stream bits ``8k …``."""
    off = np.arange(n, dtype=np.int64) * bits
    k, shift = off >> 3, (off & 7).astype(np.uint32)
    b = np.zeros(raw.size + 3, dtype=np.uint32)     # ≤ 14 bits at a shift ≤ 7 span ≤ 3 bytes
    b[:raw.size] = raw
    word = b[k] | (b[k + 1] << 8) | (b[k + 2] << 16)
    return ((word >> shift) & ((1 << bits) - 1)).astype(np.uint16)


def _unpack_grouped(raw: np.ndarray, n: int, bits: int) -> np.ndarray:
    """GigE Vision 1.x MonoNPacked: ``b0 = p0`` MSBs, ``b1`` = both pixels' low bits, ``b2 = p1`` MSBs."""
    lo = bits - 8
    b = np.zeros(3 * ((n + 1) // 2), dtype=np.uint16)   # an odd pixel count ends mid-triple
    b[:raw.size] = raw
    b = b.reshape(-1, 3)
    out = np.empty((b.shape[0], 2), dtype=np.uint16)
    mask = (1 << lo) - 1
    out[:, 0] = (b[:, 0] << lo) | (b[:, 1] & mask)
    out[:, 1] = (b[:, 2] << lo) | ((b[:, 1] >> 4) & mask)
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
    elif name in _LSB_STREAM:
        px = _unpack_lsb_stream(raw, n, SIGNIFICANT_BITS[name])
    elif name in _GROUPED:
        px = _unpack_grouped(raw, n, SIGNIFICANT_BITS[name])
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
    bits = SIGNIFICANT_BITS[name]
    if name in _LSB_STREAM:
        stream = ((px[:, None] >> np.arange(bits, dtype=np.uint16)) & 1).astype(np.uint8)
        return np.packbits(stream.reshape(-1), bitorder="little").tobytes()
    if name in _GROUPED:
        lo = bits - 8
        if px.size % 2:
            px = np.append(px, np.uint16(0))
        p = px.reshape(-1, 2)
        out = np.empty((p.shape[0], 3), dtype=np.uint8)
        mask = (1 << lo) - 1
        out[:, 0] = p[:, 0] >> lo
        out[:, 1] = ((p[:, 1] & mask) << 4) | (p[:, 0] & mask)
        out[:, 2] = p[:, 1] >> lo
        return out.tobytes()[:frame_bytes(code, n, 1)]
    return px.astype("<u2").tobytes()
