"""GenICam pixel formats against the standards' byte layouts (hand-built bytes, not mehs's packer).

Truth: EMVA PFNC 2.x (Mono10p / Mono12p / Mono14p: "lsb packing", a little-endian bit stream;
Mono10 / Mono12 / Mono14 / Mono16: LSB-aligned little-endian 16-bit words) and GigE Vision 2.0
§28 (the grouped Mono10Packed / Mono12Packed of GigE Vision 1.x: two pixels in three bytes,
MSBs first; a frame is one stream, so an odd-width line ends mid-group). Codes: PFNC.h
(Mono10p 0x010A0046, Mono10Packed 0x010C0004, Mono14p 0x010E0104).
"""

import numpy as np
import pytest

from mehs.capture import pixfmt


def _lsb_stream(px, bits):
    """The PFNC definition, literally: pixel i at stream bit i·bits; byte k = stream bits 8k…8k+7."""
    stream = 0
    for i, p in enumerate(px):
        stream |= int(p) << (bits * i)
    return stream.to_bytes((bits * len(px) + 7) // 8, "little")


@pytest.mark.parametrize("name, code", [("Mono10p", 0x010A0046), ("Mono10Packed", 0x010C0004),
                                        ("Mono14p", 0x010E0104), ("Mono12p", 0x010C0047),
                                        ("Mono12Packed", 0x010C0006), ("Mono14", 0x01100025)])
def test_pfnc_codes(name, code):
    assert pixfmt.PIXEL_FORMATS[name] == code
    assert pixfmt.name_of(code) == name


def test_mono10p_hand_built_bytes():
    # p0..p3 = 0x3FF, 0x000, 0x155, 0x2AA: b0 = p0[7:0], b1 = p1[5:0]<<2 | p0[9:8],
    # b2 = p2[3:0]<<4 | p1[9:6], b3 = p3[1:0]<<6 | p2[9:4], b4 = p3[9:2]
    px = [0x3FF, 0x000, 0x155, 0x2AA]
    data = bytes([0xFF, 0x03, 0x50, 0x95, 0xAA])
    assert data == _lsb_stream(px, 10)
    code = pixfmt.PIXEL_FORMATS["Mono10p"]
    assert pixfmt.unpack(data, code, 4, 1).tolist() == [px]
    assert pixfmt.unpack(data, code, 1, 4).reshape(-1).tolist() == px   # a frame is one stream
    assert pixfmt.pack(np.array(px, np.uint16), code) == data


def test_mono10packed_hand_built_bytes():
    # GigE Vision: b0 = p0[9:2], b1 = p1[1:0]<<4 | p0[1:0], b2 = p1[9:2]
    px = [0x2B7, 0x0C9]            # 10 1010 1101 11, 00 1100 1001
    data = bytes([0xAD, 0x13, 0x32])
    code = pixfmt.PIXEL_FORMATS["Mono10Packed"]
    assert pixfmt.unpack(data, code, 2, 1).tolist() == [px]
    assert pixfmt.pack(np.array(px, np.uint16), code) == data


def test_mono14p_hand_built_bytes():
    px = [0x3FFF, 0x0001, 0x2000, 0x1234]
    data = _lsb_stream(px, 14)
    assert len(data) == 7 == pixfmt.frame_bytes(pixfmt.PIXEL_FORMATS["Mono14p"], 4, 1)
    # spot check the spec's first two bytes: b0 = p0[7:0], b1 = p1[1:0]<<6 | p0[13:8]
    assert data[:2] == bytes([0xFF, 0x7F])
    code = pixfmt.PIXEL_FORMATS["Mono14p"]
    assert pixfmt.unpack(data, code, 4, 1).tolist() == [px]
    assert pixfmt.pack(np.array(px, np.uint16), code) == data


@pytest.mark.parametrize("name, bits", [("Mono10p", 10), ("Mono12p", 12), ("Mono14p", 14)])
def test_lsb_stream_formats_random_odd_frames(name, bits):
    rng = np.random.default_rng(bits)
    px = rng.integers(0, 1 << bits, size=(3, 7)).astype(np.uint16)   # 21 px: ends mid-group
    data = _lsb_stream(px.reshape(-1), bits)
    code = pixfmt.PIXEL_FORMATS[name]
    assert len(data) == pixfmt.frame_bytes(code, 7, 3)
    np.testing.assert_array_equal(pixfmt.unpack(data, code, 7, 3), px)
    assert pixfmt.pack(px, code) == data


def test_odd_width_grouped_frame_is_one_stream():
    # Mono12Packed 1×2 frame (width 1): line 1's pixel shares the first triple (no line padding)
    code = pixfmt.PIXEL_FORMATS["Mono12Packed"]
    assert pixfmt.unpack(bytes([0xAB, 0x3C, 0x12]), code, 1, 2).tolist() == [[0xABC], [0x123]]


@pytest.mark.parametrize("name, value", [("Mono10", 0x3A5), ("Mono12", 0xABC), ("Mono14", 0x3ABC),
                                         ("Mono16", 0xFE01)])
def test_unpacked_words_are_little_endian(name, value):
    # PFNC: LSB first in memory; GigE Vision streams pixel data little-endian (only its control
    # registers are big-endian), so 0xFE01 arrives as 01 FE
    data = bytes([value & 0xFF, value >> 8])
    assert pixfmt.unpack(data, pixfmt.PIXEL_FORMATS[name], 1, 1).tolist() == [[value]]


def test_preference_keeps_the_deepest_format():
    """A camera left in Mono8 that offers Mono12 and Mono14 has a 14-bit pipeline: Mono12 would
    drop two bits of the dynamic range an HDR capture is after."""
    offered = ["Mono8", "Mono12", "Mono14", "Mono12Packed"]
    assert [f for f in pixfmt.PREFERRED if f in offered][0] == "Mono14"
    offered = ["Mono8", "Mono10p", "Mono10"]
    assert [f for f in pixfmt.PREFERRED if f in offered][0] == "Mono10"
