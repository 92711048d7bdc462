"""Guards: `mehs export` files read against the published layouts, not against mehs's reader.

- The OpenEXR file layout (openexr.com "OpenEXR File Layout": magic, version, attribute
  ``name\\0 type\\0 size value``, ``chlist``, offset table, ZIP = zlib of 16 scan lines with
  the byte predictor and the two-half byte split) — decoded here by a small reader of its own.
- Fichet, Pacanowski & Wilkie 2021 (JCGT 10(3)) spectral layout, as its reference code
  (afichet/spectral-exr, ``EXRSpectralImage::channelType``) parses it: channel regex below,
  comma decimal, ``spectralLayoutVersion`` and ``emissiveUnits`` string attributes.
"""

import re
import struct
import zlib

import numpy as np
import OpenEXR

from mehs.cube import SpectralCube
from mehs.export import export_per_wavelength, export_spectral_exr
from mehs.io.exr import ABSOLUTE_RADIANCE, read_exr_spectral

# spectral-exr's channel expression (S0..S3 emissive, T reflective; value, SI prefix, unit)
FICHET_RE = re.compile(r"^((S([0-3]))|T)\.(\d*,?\d*([Ee][+-]?\d+)?)"
                       r"(Y|Z|E|P|T|G|M|k|h|da|d|c|m|u|n|p)?(m|Hz)$")
PREFIX_NM = {"": 1.0, "n": 1.0, "u": 1e3, "m": 1e6}      # the prefixes these tests meet
FLOAT, HALF = 2, 1                                       # OpenEXR pixel type codes
WL = np.r_[397.32, np.arange(400.0, 721.0, 5.0)]         # a Specim-like centre + 400:720:5


def _raw_exr(path):
    """(version, {name: (type, bytes)}, [(channel, pixel type)], {channel: (H, W) array})."""
    b = open(path, "rb").read()
    assert b[:4] == b"\x76\x2f\x31\x01"
    version = struct.unpack("<I", b[4:8])[0]
    pos, attrs = 8, {}

    def cstr():
        nonlocal pos
        end = b.index(b"\0", pos)
        s, pos = b[pos:end].decode(), end + 1
        return s

    while b[pos] != 0:
        name, typ = cstr(), cstr()
        size = struct.unpack("<i", b[pos:pos + 4])[0]
        attrs[name] = (typ, b[pos + 4:pos + 4 + size])
        pos += 4 + size
    pos += 1
    chl, q, chans = attrs["channels"][1], 0, []
    while chl[q] != 0:
        end = chl.index(b"\0", q)
        name, q = chl[q:end].decode(), end + 1
        chans.append((name, struct.unpack("<i", chl[q:q + 4])[0]))
        q += 16
    x0, y0, x1, y1 = struct.unpack("<4i", attrs["dataWindow"][1])
    w, h = x1 - x0 + 1, y1 - y0 + 1
    comp = attrs["compression"][1][0]
    per_chunk = {0: 1, 2: 1, 3: 16}[comp]
    n_chunks = -(-h // per_chunk)
    dtypes = {HALF: np.dtype("<f2"), FLOAT: np.dtype("<f4")}
    out = {c: np.empty((h, w), np.float32) for c, _ in chans}
    for off in struct.unpack(f"<{n_chunks}Q", b[pos:pos + 8 * n_chunks]):
        y, size = struct.unpack("<ii", b[off:off + 8])
        data = b[off + 8:off + 8 + size]
        rows = min(per_chunk, y1 - y + 1)
        if comp != 0 and size < sum(dtypes[t].itemsize for _, t in chans) * w * rows:
            d = np.frombuffer(zlib.decompress(data), np.uint8).astype(np.int64)
            t = ((np.cumsum(d - 128) + 128) & 0xFF).astype(np.uint8)   # undo the predictor
            split = (t.size + 1) // 2
            inter = np.empty_like(t)
            inter[0::2], inter[1::2] = t[:split], t[split:]
            data = inter.tobytes()
        p = 0
        for r in range(rows):
            for c, t in chans:
                k = dtypes[t].itemsize * w
                out[c][y - y0 + r] = np.frombuffer(data[p:p + k], dtypes[t])
                p += k
    return version, attrs, chans, out


def _string(attrs, name):
    typ, value = attrs[name]
    assert typ == "string", (name, typ)
    return value.decode()


def _fichet_nm(name):
    m = FICHET_RE.match(name)
    assert m, name
    return float(m.group(4).replace(",", ".")) * PREFIX_NM[m.group(6) or ""]


def _cube():
    rng = np.random.default_rng(22)
    data = rng.uniform(0.01, 900.0, (3, 5, WL.size)).astype(np.float32)   # 3 lines × 5 samples
    data[0, 0] = 5.0e4                                                    # a lamp, in half range
    return SpectralCube(data, WL, units=ABSOLUTE_RADIANCE)


def test_spectral_exr_follows_the_fichet_layout(tmp_path):
    cube = _cube()
    for half, ptype in ((False, FLOAT), (True, HALF)):
        version, attrs, chans, px = _raw_exr(export_spectral_exr(cube, tmp_path / f"{half}.exr",
                                                                 half=half))
        assert version == 2                                   # single-part scan-line file
        assert _string(attrs, "spectralLayoutVersion") == "1.0"
        assert _string(attrs, "emissiveUnits") == "W.m^-2.sr^-1"
        names = [c for c, _ in chans]
        assert names == sorted(names) and all(n.startswith("S0.") for n in names)
        assert {t for _, t in chans} == {ptype}
        nm = np.array([_fichet_nm(n) for n in names])
        order = np.argsort(nm)
        np.testing.assert_array_equal(nm[order], WL)            # exact, comma decimal
        assert {"S0.397,32nm", "S0.405nm", "S0.720nm"} <= set(names)
        assert attrs["wavelengths"][0] == "floatvector"
        np.testing.assert_array_equal(np.frombuffer(attrs["wavelengths"][1], "<f4"),
                                      WL.astype(np.float32))
        got = np.stack([px[names[i]] for i in order], axis=-1)
        tol = 2.0 ** -11 * np.abs(cube.data) if half else 0.0   # half: round to 11 bits
        assert np.all(np.abs(got - cube.data) <= tol)


def test_per_wavelength_files_against_the_cube(tmp_path):
    cube = _cube()
    for half, ptype in ((False, FLOAT), (True, HALF)):
        paths = export_per_wavelength(cube, tmp_path / str(half), half=half)
        assert [p.name for p in paths] == [f"band_{i:03d}.exr" for i in range(WL.size)]
        for i, p in enumerate(paths):
            version, attrs, chans, px = _raw_exr(p)
            assert version == 2 and chans == [("Y", ptype)]
            window = struct.pack("<4i", 0, 0, 4, 2)               # x 0..4 samples, y 0..2 lines
            assert attrs["dataWindow"] == ("box2i", window) == \
                (attrs["displayWindow"][0], attrs["displayWindow"][1])
            assert attrs["lineOrder"] == ("lineOrder", b"\x00")  # INCREASING_Y: row 0 first
            assert attrs["compression"] == ("compression", b"\x03")   # ZIP
            assert struct.unpack("<f", attrs["wavelength"][1])[0] == np.float32(WL[i])
            tol = 2.0 ** -11 * np.abs(cube.data[:, :, i]) if half else 0.0
            assert np.all(np.abs(px["Y"] - cube.data[:, :, i]) <= tol)   # rows = lines


def test_a_file_in_the_layouts_conventions_reads_in_wavelength_order(tmp_path):
    """Written as spectral-exr writes (``std::to_string`` names, an RGB preview, S0–S3,
    half pixels): read by name order, "S0.1000,000000nm" would come first."""
    wl = [380.0, 397.5, 1000.0]
    h, w = 2, 3
    planes = {f"S{s}.{f'{x:.6f}'.replace('.', ',')}nm":
              np.full((h, w), 10.0 * s + k + 1, np.float16)
              for s in range(4) for k, x in enumerate(wl)}
    planes.update({c: np.full((h, w), 0.5, np.float16) for c in "RGB"})
    path = tmp_path / "fichet.exr"
    OpenEXR.File({"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION,
                  "spectralLayoutVersion": "1.0", "emissiveUnits": "W.m^-2.sr^-1",
                  "polarisationHandedness": "right"}, planes).write(str(path))
    cube = read_exr_spectral(path)
    np.testing.assert_array_equal(cube.wavelengths, wl)
    np.testing.assert_array_equal(cube.data[0, 0], [1.0, 2.0, 3.0])   # S0, ascending λ
    assert cube.units == ABSOLUTE_RADIANCE
