"""Spectral image-based lighting on Mitsuba 3 (render extra): emitter, renders, CLI, page.

Truths: colour-science's illuminant spectra (a white Lambertian sphere under a uniform map
reflects exactly the map's spectrum), Mitsuba's own ``envmap`` (texel layout), Monte-Carlo
vs quadrature of the same map (importance sampling), headless Chromium (the page).
"""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from mehs.capture.scene import illuminant_spectrum, make_scene  # noqa: E402
from mehs.cli import main  # noqa: E402
from mehs.cube import SpectralCube  # noqa: E402
from mehs.errors import InputError  # noqa: E402
from mehs.io.envi import write_envi  # noqa: E402
from mehs.render.maps import EnvMap, load_envmap, rgb_map, ssr_map, uniform_map  # noqa: E402
from mehs.render.scene import RenderSettings, render_spectral  # noqa: E402
from mehs.render.smits_pbrt import SmitsPBRT  # noqa: E402
from mehs.rgb import WAVELENGTHS_31, hdr_rgb  # noqa: E402
from mehs.ssr.models import load_model  # noqa: E402

TOOLS = Path(__file__).resolve().parents[1] / "tools"
WL = WAVELENGTHS_31


def sphere_mask(s: RenderSettings, shrink: float = 0.85) -> np.ndarray:
    """Pixels well inside the sphere's silhouette (the camera frames it at 70 % of the view)."""
    half = math.radians(s.fov / 2)
    alpha = math.asin(0.7 * math.sin(half))
    r_px = math.tan(alpha) / math.tan(half) * min(s.width, s.height) / 2 * shrink
    yy, xx = np.mgrid[0:s.height, 0:s.width] + 0.5
    return (yy - s.height / 2) ** 2 + (xx - s.width / 2) ** 2 < r_px ** 2


def angle_deg(a, b):
    return math.degrees(math.acos(min(1.0, float(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))))


def test_emitter_matches_mitsuba_envmap_layout_and_samples_consistently():
    from mehs.render.plugins import plugin_classes

    rng = np.random.default_rng(1)
    env = EnvMap(rng.uniform(0.1, 2.0, (6, 12, WL.size)).astype(np.float32), WL)
    # a bright "lamp" pixel so importance sampling has something to find
    env.radiance[2, 7] *= 200
    HSEnvmap, _ = plugin_classes("scalar_spectral")
    em = HSEnvmap(mi.Properties(), envmap=env)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lam = mi.Spectrum(450.0, 520.0, 589.0, 650.0)
    ours = []
    for d in dirs:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))
        si.wavelengths = lam
        ours.append([em.eval(si)[i] for i in range(4)])
    ours = np.array(ours)
    spec = _spectra_at(em, dirs)
    expect = np.stack([_interp_bands(spec, l) for l in (450, 520, 589, 650)], -1)
    assert np.allclose(ours, expect, rtol=1e-5)
    # the RGB of our per-pixel spectra equals what Mitsuba's envmap returns from the RGB map
    mi.set_variant("scalar_rgb")
    stock = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(rgb_map(env))})
    theirs = []
    for d in dirs:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))
        v = stock.eval(si)
        theirs.append([v[0], v[1], v[2]])
    mi.set_variant("scalar_spectral")
    ours_rgb = hdr_rgb(np.array(_spectra_at(em, dirs))[None], WL)[0]
    assert np.allclose(ours_rgb, np.array(theirs), rtol=1e-4, atol=1e-5)

    # sampling: pdf of a sample equals pdf_direction, and E[L/pdf] = ∫ L dω (quadrature)
    it = mi.Interaction3f()
    it.wavelengths = lam
    est, n = np.zeros(4), 4000
    u = rng.random((n, 2))
    for a, b in u:
        ds, w = em.sample_direction(it, mi.Point2f(a, b))
        if ds.pdf > 0:
            assert em.pdf_direction(it, ds) == pytest.approx(ds.pdf, rel=1e-3)  # float32 d
        est += [w[i] for i in range(4)]
    est /= n
    th = (np.arange(300) + 0.5) / 300 * np.pi
    ph = (np.arange(600) + 0.5) / 600 * 2 * np.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    grid = np.stack([np.sin(T) * np.sin(P), np.cos(T), -np.sin(T) * np.cos(P)], -1).reshape(-1, 3)
    spec = _spectra_at(em, grid)
    vals = np.stack([_interp_bands(spec, l) for l in (450, 520, 589, 650)], -1).reshape(300, 600, 4)
    quad = (vals * np.sin(T)[..., None]).sum((0, 1)) * (np.pi / 300) * (2 * np.pi / 600)
    assert np.allclose(est, quad, rtol=0.03), (est, quad)


def _interp_bands(spec, lam):
    j = int(np.searchsorted(WL, lam, side="right")) - 1
    t = (lam - WL[j]) / (WL[j + 1] - WL[j])
    return spec[:, j] * (1 - t) + spec[:, j + 1] * t


def _spectra_at(em, dirs):
    """Bilinear map look-up in Mitsuba's envmap layout, re-implemented with numpy."""
    d = np.asarray(dirs, np.float64)
    data = em._data[..., 1:-1]
    h, w = data.shape[:2]
    u = (np.arctan2(d[:, 0], -d[:, 2]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(d[:, 1], -1, 1)) / np.pi
    x = u * w - 0.5
    x0 = np.floor(x).astype(int)
    fx = (x - x0)[:, None]
    x0 %= w
    x1 = (x0 + 1) % w
    y = v * (h - 1)
    y0 = np.minimum(y.astype(int), h - 2)
    fy = (y - y0)[:, None]
    return ((1 - fy) * ((1 - fx) * data[y0, x0] + fx * data[y0, x1])
            + fy * ((1 - fx) * data[y0 + 1, x0] + fx * data[y0 + 1, x1]))


def test_white_lambertian_sphere_returns_uniform_map_spectrum():
    L = illuminant_spectrum("A", WL)
    L = L / L.mean()
    # 16 film bands (every 20 nm) so each band collects enough wavelength samples for a
    # 2 % check at a test-sized budget; the map keeps its 31 bands
    bands = tuple(float(b) for b in WL[::2])
    s = RenderSettings(width=32, height=32, spp=121, material="diffuse", bands=bands)
    img = render_spectral(s, hs_map=uniform_map(L, WL))
    mean = img[sphere_mask(s, 0.95)].mean(axis=0)
    L = L[::2]
    err = np.abs(mean / L - 1)
    print(f"\nwhite sphere under a uniform CIE A map: max band error {err.max():.4f}, "
          f"spectral angle {angle_deg(mean, L):.3f}°")
    assert err.max() <= 0.02


def test_hp1_reflection_spectral_angle_hs_vs_rgb_upsampled(capsys):
    hp1 = illuminant_spectrum("HP1", WL)
    env = uniform_map(hp1 / hp1.mean(), WL)
    s = RenderSettings(width=32, height=32, spp=121, material="diffuse")
    # the up-sampled paths are off by far more than their noise: a cheaper render will do
    quick = RenderSettings(width=24, height=24, spp=25, material="diffuse")
    rgb = rgb_map(env)
    imgs = {
        "hs": (s, render_spectral(s, hs_map=env)),
        "smits-pbrt": (quick, render_spectral(quick, hs_map=ssr_map(rgb, SmitsPBRT()))),
        "smits-mehs": (quick, render_spectral(quick, hs_map=ssr_map(rgb, load_model("smits")))),
        "jakob": (quick, render_spectral(quick, rgb_map=rgb)),
    }
    angles = {k: angle_deg(img[sphere_mask(st)].mean(axis=0), hp1) for k, (st, img) in imgs.items()}
    with capsys.disabled():
        print("\nspectral angle of the white sphere's reflection to CIE HP1: "
              + ", ".join(f"{k} {v:.2f}°" for k, v in angles.items()))
    assert angles["hs"] <= 2.0
    assert min(angles["smits-pbrt"], angles["smits-mehs"], angles["jakob"]) > 10.0


def test_map_readers_agree_and_refuse_bad_maps(tmp_path):
    from mehs.export import export_per_wavelength, export_spectral_exr

    rng = np.random.default_rng(3)
    cube = SpectralCube(rng.uniform(0, 5, (4, 8, WL.size)).astype(np.float32), WL,
                        units="relative radiance")
    write_envi(tmp_path / "m.hdr", cube)
    export_per_wavelength(cube, tmp_path / "bands")
    export_spectral_exr(cube, tmp_path / "m.exr")
    maps = [load_envmap(p) for p in (tmp_path / "m.hdr", tmp_path / "bands", tmp_path / "m.exr")]
    for m in maps:
        assert np.array_equal(m.radiance, cube.data) and np.allclose(m.wavelengths, WL)
    (tmp_path / "bands" / "band_005.exr").unlink()
    with pytest.raises(InputError, match="band_005.exr"):
        load_envmap(tmp_path / "bands")
    bad = cube.data.copy()
    bad[0, 0, 0] = -1
    with pytest.raises(InputError, match="negative"):
        EnvMap(bad, WL)
    raw = SpectralCube(np.ones((4, 8, WL.size), np.uint16), WL, units="DN")
    write_envi(tmp_path / "raw.hdr", raw)
    with pytest.raises(InputError, match="raw counts"):
        load_envmap(tmp_path / "raw.hdr")


def test_mesh_object_renders(tmp_path):
    """A .obj mesh (a unit cube written here) is framed and lit like the sphere."""
    v = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    text = "".join(f"v {a} {b} {c}\n" for a, b, c in v)
    text += "".join(f"f {a} {b} {c}\nf {a} {c} {d}\n" for a, b, c, d in quads)
    (tmp_path / "cube.obj").write_text(text)
    s = RenderSettings(width=12, height=12, spp=4, material="diffuse:0.5",
                       object=str(tmp_path / "cube.obj"), bands=(550.0,))
    img = render_spectral(s, hs_map=uniform_map(np.ones(WL.size), WL))[..., 0]
    # centre: the cube's face, ρ = 0.5 of a uniform unit map; corners: the map itself
    assert img[5:7, 5:7].mean() == pytest.approx(0.5, rel=0.15)
    assert img[0, 0] == pytest.approx(1.0, rel=1e-3)


def _sodium_lamp_map(path: Path) -> Path:
    """The demo's sodium-lamp scene (D65 dusk, HP1 lamp in view) as a 31-band map."""
    sc = make_scene("lamp", lines=16, samples=32, wavelengths=WL, illuminant="D65",
                    light_source="HP1", source_ratio=300.0, seed=0)
    write_envi(path, SpectralCube(np.asarray(sc.radiance, np.float32), WL,
                                  units="relative radiance"))
    return path


def test_cli_render_sodium_lamp_scene_writes_renders_differences_and_page(tmp_path, capsys):
    hs = _sodium_lamp_map(tmp_path / "lamp.hdr")
    out = tmp_path / "render"
    assert main(["render", str(hs), "--out", str(out), "--size", "24x24", "--spp", "4",
                 "--ssr", "mallett", "--ssr-input", "both", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "mean ΔE2000" in text and "ssr-mallett" in text
    doc = json.loads((out / "render.json").read_text())
    names = [r["name"] for r in doc["results"]]
    assert names == ["hs", "rgb", "smits", "jakob", "ssr-mallett", "ssr-mallett-ldr"]
    for r in doc["results"]:
        for key in ("exr", "png") + (("diff_png",) if r["name"] != "hs" else ()):
            assert (out / r[key]).is_file(), r[key]
        if r["name"] != "hs":
            assert r["mean_delta_E2000"] > 0 and 0 < r["relative_error"] < 10
    assert (out / "index.html").is_file() and (out / "rgb_diff_x5.png").is_file()
    # bad input: a clear error naming the problem, no traceback, no output folder
    for args, msg in ((["--material", "gold"], "--material"),
                      (["--object", str(tmp_path / "none.obj")], "none.obj"),
                      (["--size", "0x5"], "--size")):
        assert main(["render", str(hs), "--out", str(tmp_path / "x")] + args) == 2
        assert msg in capsys.readouterr().err
    assert main(["render", str(tmp_path / "nope.hdr"), "--out", str(tmp_path / "x")]) == 2
    assert "nope.hdr" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()

    sys.path.insert(0, str(TOOLS))
    try:
        import check_report_chromium as chk
    finally:
        sys.path.pop(0)
    if chk.find_chromium() is None:
        pytest.skip("chromium is not installed")
    res = chk.check_report(out / "index.html")
    assert res["images"] == 2 * len(names) and res["broken"] == []
    (out / "smits_diff_x5.png").write_bytes(b"not a png")
    assert chk.check_report(out / "index.html")["broken"] == ["smits_diff_x5.png"]


def test_ldr_map_keeps_the_scene_and_clips_the_lamp():
    from mehs.render.run import ldr_map

    rgb = np.full((8, 16, 3), 0.2, np.float32)
    rgb[..., 0] = 0.3
    rgb[2, 3] = 500.0
    ldr = ldr_map(rgb)
    assert np.allclose(ldr[5, 5], rgb[5, 5], rtol=0.03)      # 8-bit quantisation only
    assert ldr[2, 3].max() < 0.05 * 500.0                     # the lamp is clipped
