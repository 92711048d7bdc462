"""Review leftovers of round 20: the MATLAB reader below both SSR dataset modules, the shared
sampler's public name, one region parse per calibration, a simulated GigE Vision rig that
closes at any point, and failed buffers that a drain re-queues being counted."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import types

import numpy as np
import pytest
import scipy.io

from _checks import write_mat73
from mehs.errors import DeviceError, FormatError, InputError


# ------------------------------------------------------------------ 1. MATLAB reader
def _harvard_like(h=6, w=5, seed=0):
    rng = np.random.default_rng(seed)
    ref = rng.uniform(0.0, 1.0, (h, w, 31))
    lbl = np.ones((h, w))
    lbl[0, :2] = 0
    return ref, lbl


def test_mat_reader_lives_below_both_dataset_modules(tmp_path):
    from mehs.io import matfile, ssr_datasets

    ref, lbl = _harvard_like()
    v5 = tmp_path / "img1.mat"
    scipy.io.savemat(v5, {"ref": ref, "lbl": lbl})
    v73 = write_mat73(tmp_path / "img2.mat", {"ref": ref, "lbl": lbl})
    for f in (v5, v73):        # MATLAB's axis order from either version, as numpy wrote it
        got = matfile.read_mat_variables(f, ("ref", "lbl"))
        np.testing.assert_array_equal(got["ref"], ref)
        np.testing.assert_array_equal(got["lbl"], lbl)
    with pytest.raises(FormatError, match=r"no variable 'rad'.*variables: lbl, ref"):
        matfile.read_mat_variables(v5, ("rad",))
    with pytest.raises(InputError, match="no such file"):
        matfile.read_mat_variables(tmp_path / "none.mat", ("ref",))
    # the old home still answers (ssr_kaist and outside code import it from there)
    assert ssr_datasets.read_mat_variables is matfile.read_mat_variables


def test_harvard_reader_does_not_import_the_datasets_module(tmp_path):
    ref, lbl = _harvard_like(seed=3)
    f = tmp_path / "imga1.mat"
    scipy.io.savemat(f, {"ref": ref, "lbl": lbl})
    code = ("import json, sys\n"
            "from mehs.io.ssr_harvard import harvard_mask, read_harvard\n"
            f"cube, bands, _ = read_harvard({str(f)!r})\n"
            f"m = harvard_mask(__import__('pathlib').Path({str(f)!r}))\n"
            "print(json.dumps({'loaded': 'mehs.io.ssr_datasets' in sys.modules,\n"
            "                  'sum': float(cube.sum()), 'masked': int((m == 2).sum())}))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["loaded"] is False
    assert got["sum"] == pytest.approx(float(ref.sum()), rel=1e-12)
    assert got["masked"] == int((lbl == 0).sum()) == 2


# ------------------------------------------------------------------ 2. shared sampler
def test_shared_sampler_is_public_and_fills_short_channels_with_weightless_slots():
    from mehs.synthesis import response_select
    from mehs.synthesis.fuse_response import sample_shared

    bit_depth, L = 8, 256
    rng = np.random.default_rng(5)
    P, M, C = 3, 400, 2
    cand = rng.integers(1, L - 1, (P, M, C)).astype(np.int32)
    cand[:, 10:, 1] = L - 1            # channel 1: only 10 pixels usable
    Z, idx = sample_shared(cand, 40, seed=2, bit_depth=bit_depth)
    assert Z.shape == (40, P, C) and Z.dtype == np.int32 and idx.shape == (C, 40)
    assert (idx[0] >= 0).all() and len(set(idx[0].tolist())) == 40
    assert (idx[1] >= 0).sum() <= 10 and (idx[1] < 0).any()
    for c in range(C):                 # by hand: Z is cand at the picked pixels, L−1 unfilled
        for k in range(40):
            want = cand[:, idx[c, k], c] if idx[c, k] >= 0 else np.full(P, L - 1)
            np.testing.assert_array_equal(Z[k, :, c], want)
    Z2, idx2 = sample_shared(cand, 40, seed=2, bit_depth=bit_depth)
    np.testing.assert_array_equal(idx, idx2)
    # held-out pixels: the same sampler, none of the used ones
    cdark = np.zeros(cand.shape, np.float32)
    Zh, Dh = response_select.held_out_samples(cand, cdark, idx, 40, 3, bit_depth)
    assert Zh.shape == Dh.shape == (40, P, C)
    used0 = {tuple(cand[:, i, 0]) for i in idx[0]}
    assert not any(tuple(Zh[k, :, 0]) in used0 for k in range(40))


# ------------------------------------------------------------------ 3. calibration region
@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    from mehs.cli import main

    out = tmp_path_factory.mktemp("h20cal") / "sphere"
    assert main(["capture", "--simulate", "--scene", "sphere", "--size", "12", "--out", str(out),
                 "--no-progress"]) == 0
    return out


@pytest.mark.parametrize("region", ["frame", "lines:2-5"])
def test_calibration_parses_its_region_once(sphere, monkeypatch, region):
    from mehs.calibration import calibrate as cal_mod
    from mehs.calibration import calibrate_source_absolute, load_spectrum
    from mehs.synthesis.bracket import load_bracket

    calls = []
    real = cal_mod._region_rows
    monkeypatch.setattr(cal_mod, "_region_rows", lambda r, b: calls.append(r) or real(r, b))
    br = load_bracket(sphere)
    cal = calibrate_source_absolute(br, load_spectrum(sphere / "truth" / "source_radiance.csv"),
                                    region=region)
    assert calls == [region]
    truth = np.asarray(json.loads((sphere / "scene.json").read_text())
                       ["truth_dn_per_ms_per_radiance"])
    ratio = cal.responsivity / truth[None, :]
    assert abs(np.median(ratio) - 1) < 0.005


# ------------------------------------------------------------------ 4. GenICam rig close()
def _rig(**kw):
    from mehs.capture.aravis import aravis_available

    why = aravis_available()
    if why is not None:
        pytest.skip(f"Aravis unavailable: {why}")
    from mehs.capture.genicam_sim import SimGenicamDevices
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel

    return SimGenicamDevices(make_scene("ramp", lines=4, samples=8, seed=1), SensorModel(seed=1),
                             start_homed=True, **kw)


def _port_free(port: int) -> bool:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        s.bind(("127.0.0.1", port))
        return True
    except OSError:
        return False
    finally:
        s.close()


def test_rig_closes_before_start_and_twice():
    dev = _rig()
    port, tmp = dev.server.port, dev.camera._tmp
    assert not _port_free(port)
    dev.close()
    dev.close()
    assert _port_free(port) and not tmp.exists()


def test_rig_closes_after_a_failed_start(monkeypatch):
    dev = _rig()
    port = dev.server.port

    def refuse():
        raise DeviceError("cannot serve the simulated GigE Vision camera (test)")

    monkeypatch.setattr(dev.camera, "start", refuse)
    with pytest.raises(DeviceError, match="test"):
        dev.start()
    dev.close()
    assert _port_free(port)


def test_rig_that_fails_to_build_frees_its_stage_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(InputError, match="pixel format") as info:
        _rig(port=port, pixel_format="Mono10")
    assert info.value is not None    # the traceback (and the half-built rig) still alive here
    assert _port_free(port)


@pytest.mark.usefixtures("gvcp_port_turns")
def test_rig_closes_after_serving_and_twice():
    dev = _rig()
    port = dev.server.port
    with dev:
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass
    dev.close()
    assert _port_free(port)


# ------------------------------------------------------------------ 5. drained failed buffers
class _Buf:
    def __init__(self, fid, ok):
        self.fid, self.ok = fid, ok

    def get_status(self):
        return _Status.SUCCESS if self.ok else _Status.INCOMPLETE

    def get_frame_id(self):
        return self.fid


class _Nick:
    def __init__(self, nick):
        self.value_nick = nick


class _Status:
    SUCCESS = _Nick("success")
    INCOMPLETE = _Nick("missing-packets")


class _Stream:
    def __init__(self, bufs):
        self.bufs, self.pushed = list(bufs), []

    def try_pop_buffer(self):
        return self.bufs.pop(0) if self.bufs else None

    def push_buffer(self, b):
        self.pushed.append(b)


@pytest.mark.parametrize("with_ledger", [True, False])
def test_drain_counts_the_failed_buffers_it_requeues(with_ledger):
    from mehs.capture.genicam import GenicamCamera
    from mehs.capture.genicam_frames import TriggerLedger

    cam = GenicamCamera.__new__(GenicamCamera)
    cam.Aravis = types.SimpleNamespace(BufferStatus=_Status)
    cam.events, cam.lost_buffers = [], 0
    cam._stream = _Stream([_Buf(7, True), _Buf(8, False), _Buf(9, False)])
    cam._drain(TriggerLedger("test") if with_ledger else None)
    assert len(cam._stream.pushed) == 3                   # every buffer goes back to the pool
    assert cam.lost_buffers == 2                          # as _pop counts a failed buffer
    lost = [e for e in cam.events if "lost / incomplete" in e]
    assert len(lost) == 2 and "buffer 8 missing-packets" in lost[0]
    assert sum("dropped frame 7" in e for e in cam.events) == int(with_ledger)
