"""Constant-velocity scans (frame → line assignment, the serial path) and GenICam pixel formats.

None of these needs Aravis.
"""

import numpy as np
import pytest

from mehs.capture import pixfmt
from mehs.capture.spectral_cal import polynomial_wavelengths, read_calibration
from mehs.capture.scan import assign_frames
from mehs.errors import InputError


# ------------------------------------------------------------------ pixel formats
def _bits_reference(px, layout):
    """Bit-by-bit packing as the standards word it (independent of pixfmt's vectorised code)."""
    out = bytearray()
    for i in range(0, len(px), 2):
        p0, p1 = int(px[i]), int(px[i + 1]) if i + 1 < len(px) else 0
        if layout == "Mono12Packed":   # GigE Vision 1.x: MSBs first, shared byte holds both nibbles
            out += bytes([p0 >> 4, ((p1 & 0xF) << 4) | (p0 & 0xF), p1 >> 4])
        else:                          # PFNC Mono12p: LSB-first bit stream
            stream = p0 | (p1 << 12)
            out += bytes([(stream >> s) & 0xFF for s in (0, 8, 16)])
    return bytes(out)[:(12 * len(px) + 7) // 8]


@pytest.mark.parametrize("layout", ["Mono12Packed", "Mono12p"])
def test_packed_12bit_matches_the_standards_bit_layout(layout):
    rng = np.random.default_rng(1)
    px = rng.integers(0, 4096, size=(7, 5)).astype(np.uint16)    # odd count: a half-filled last triple
    px[0, :3] = [0, 4095, 0xABC]
    code = pixfmt.PIXEL_FORMATS[layout]
    packed = pixfmt.pack(px, code)
    assert packed == _bits_reference(px.reshape(-1), layout)
    # a 7×5 frame is 35 pixels = 52.5 bytes → 53
    assert pixfmt.frame_bytes(code, 5, 7) == 53 == len(packed)
    np.testing.assert_array_equal(pixfmt.unpack(packed, code, 5, 7), px)


def test_known_bytes_unpack_per_standard():
    # p0 = 0xABC, p1 = 0x123
    for name, data in (("Mono12Packed", [0xAB, 0x3C, 0x12]), ("Mono12p", [0xBC, 0x3A, 0x12]),
                       ("Mono16", [0xBC, 0x0A, 0x23, 0x01])):
        px = pixfmt.unpack(bytes(data), pixfmt.PIXEL_FORMATS[name], 2, 1)
        assert px.tolist() == [[0xABC, 0x123]], name


def test_bad_frames_are_value_errors():
    with pytest.raises(ValueError, match="needs 6 bytes, got 5"):
        pixfmt.unpack(b"\0" * 5, pixfmt.PIXEL_FORMATS["Mono12"], 3, 1)
    with pytest.raises(ValueError, match="not a monochrome format"):
        pixfmt.unpack(b"\0" * 6, 0x02180014, 2, 1)          # RGB8
    with pytest.raises(ValueError, match="exceed 12 bits"):
        pixfmt.pack(np.array([4096], np.uint16), pixfmt.PIXEL_FORMATS["Mono12"])
    assert pixfmt.bits_per_pixel(pixfmt.PIXEL_FORMATS["Mono12Packed"]) == 12


# ------------------------------------------------------------------ spectral calibration
def test_polynomial_wavelengths_binned_centres():
    a, b, c = 1e-4, 2.0, 400.0
    wl = polynomial_wavelengths((a, b, c), 4, binning=2, offset=10)
    x = np.array([10.5, 12.5, 14.5, 16.5])
    np.testing.assert_allclose(wl, a * x**2 + b * x + c)


def test_calibration_file(tmp_path):
    p = tmp_path / "wl.txt"
    p.write_text("400.5, 402.5\n404.5\n")
    np.testing.assert_array_equal(read_calibration(p), [400.5, 402.5, 404.5])
    p.write_text("400 399")
    with pytest.raises(InputError, match="increasing"):
        read_calibration(p)
    with pytest.raises(InputError, match="cannot read"):
        read_calibration(tmp_path / "missing.txt")


# ------------------------------------------------------------------ frame assignment
def test_assign_frames_picks_nearest_and_reports_duplicates():
    u = np.array([-0.6, -0.1, 0.4, 0.55, 1.1, 1.45, 2.0, np.nan, 3.2])
    chosen, dups, offset = assign_frames(u, 4)
    assert chosen.tolist() == [1, 4, 6, 8]
    assert dups == 3            # 0.4 (line 0), 1.45 (line 1) and 0.55 (line 1) lost to nearer frames
    np.testing.assert_allclose(offset, [0.1, 0.1, 0.0, 0.2])


def test_assign_frames_leaves_gaps_missing_never_filled():
    chosen, dups, offset = assign_frames(np.array([0.0, 1.0, 3.0]), 4)
    assert chosen.tolist() == [0, 1, -1, 2] and dups == 0 and np.isnan(offset[2])


# ------------------------------------------------------------------ serial camera, continuous
def test_serial_continuous_scan_matches_step_truth(tmp_path):
    from mehs.capture import scenefolder as sf
    from mehs.cli import main

    args = ["capture", "--simulate", "--size", "12", "--seed", "5", "--times", "1,4",
            "--dark-lines", "2", "--white-lines", "2", "--no-progress"]
    assert main(args + ["--out", str(tmp_path / "step")]) == 0
    assert main(args + ["--out", str(tmp_path / "cont"), "--scan", "continuous"]) == 0
    step, cont = sf.read_scene_json(tmp_path / "step"), sf.read_scene_json(tmp_path / "cont")
    assert cont["plan"]["scan"] == "continuous"
    from mehs.io.envi import read_envi

    for a, b in zip(step["exposures"], cont["exposures"]):
        info = b["stage"]["scan"]
        assert info["missing_lines"] == 0 and info["frames"] >= 12
        name_a, name_b = a["folder"].split("/")[-1], b["folder"].split("/")[-1]
        ra = np.asarray(read_envi(tmp_path / "step" / a["folder"] / "capture" / f"{name_a}.hdr").data, float)
        rb = np.asarray(read_envi(tmp_path / "cont" / b["folder"] / "capture" / f"{name_b}.hdr").data, float)
        # the serial simulator exposes the world line under the stage: the same scene, other noise
        good = (ra < 4000) & (rb < 4000)
        assert abs(np.median(rb[good] - ra[good])) < 2.0
        assert np.corrcoef(ra[good], rb[good])[0, 1] > 0.99


# ------------------------------------------------------------------ without Aravis
def test_missing_aravis_names_the_install_steps(monkeypatch, tmp_path):
    import sys

    from mehs.capture import aravis
    from mehs.errors import DeviceError

    monkeypatch.setitem(sys.modules, "gi", None)              # `import gi` fails
    monkeypatch.setattr(aravis, "_DEBIAN_GI", tmp_path / "no-gi")
    with pytest.raises(aravis.AravisUnavailable, match=r"gir1\.2-aravis-0\.8.*mehs\[aravis\]"):
        aravis.import_aravis()
    assert "apt-get install" in aravis.aravis_available()
    assert issubclass(aravis.AravisUnavailable, DeviceError)
    assert aravis.is_genicam_url("genicam://X") and not aravis.is_genicam_url("socket://h:1")


def test_stage_speed_settings_are_in_zabers_unit():
    """``set maxspeed`` counts 1/1.6384 microsteps/s (Zaber's default 153600 is 93750
    microsteps/s); the simulated stage moves at that speed, so a scan that sent
    microsteps/s as the setting would run at 61 % of its plan."""
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simdevice import SimWorld
    from mehs.capture.zaber import speed_from_setting, speed_setting

    assert speed_setting(93750) == 153600 and speed_from_setting(153600) == 93750
    w = SimWorld(make_scene(lines=8, samples=4), SensorModel(), speed=20000)
    assert w.maxspeed == speed_setting(20000)
    w.start_move(2000)
    assert w._move[3] == pytest.approx(0.1, rel=1e-4)          # 2000 microsteps at 20000/s


def test_genicam_wavelengths_take_offset_y_in_binned_rows():
    """SFNC: binning shrinks the image first, then OffsetY selects rows of the binned image;
    the calibration polynomial counts full-resolution rows (binning 2, OffsetY 10 = row 20)."""
    from mehs.capture.genicam import GenicamCamera

    feats = {"Width": 8, "Height": 4, "BinningVertical": 2, "OffsetY": 10,
             "WavelengthCoefficientA": 1e-4, "WavelengthCoefficientB": 1.35,
             "WavelengthCoefficientC": 400.0}
    cam = GenicamCamera.__new__(GenicamCamera)
    cam._calibration = None
    cam._has = lambda f: f in feats
    cam._int = lambda f: int(feats[f])
    cam._float = lambda f: float(feats[f])
    coeffs = (feats["WavelengthCoefficientA"], feats["WavelengthCoefficientB"],
              feats["WavelengthCoefficientC"])
    np.testing.assert_allclose(cam.wavelengths(),
                               np.round(polynomial_wavelengths(coeffs, 4, binning=2, offset=20), 3))
