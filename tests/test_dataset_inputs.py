"""The dataset builder: scene keys, unknown quality figures and the inputs it accepts."""

import numpy as np

from mehs.cube import SpectralCube
from mehs.dataset.build import build_from_hs
from mehs.io.envi import write_envi

WL31 = np.arange(400.0, 701.0, 10.0)


def test_hs_cube_with_bin_data_file_is_rebuilt_when_its_data_changes(tmp_path):
    """The scene key must cover the data file the ENVI reader opens (here ``c.bin``):
    hashing only the header reused the old outputs after the cube's values changed."""
    data = np.full((3, 4, 31), 0.5, np.float32)
    write_envi(tmp_path / "in" / "c.hdr", SpectralCube(data, WL31), dtype=np.float32,
               data_ext=".dat")
    (tmp_path / "in" / "c.dat").rename(tmp_path / "in" / "c.bin")
    m = build_from_hs([tmp_path / "in" / "c.hdr"], tmp_path / "ds", workers=1, progress=False)
    first = m["scenes"][0]["quality"]["peak_hdr_rgb"]
    assert "c.bin" in m["scenes"][0]["provenance"]["input_sha256"]

    mm = np.memmap(tmp_path / "in" / "c.bin", dtype="<f4", mode="r+")
    mm[:] = mm * 4
    mm.flush()
    del mm
    m = build_from_hs([tmp_path / "in" / "c.hdr"], tmp_path / "ds", workers=1, progress=False)
    assert m["scenes"][0]["quality"]["peak_hdr_rgb"] == np.float32(4 * first)


def test_ghost_fraction_is_unknown_not_zero_when_detection_is_off(tmp_path):
    """With ``ghosts="off"`` nothing is tested: a scene the simulator moved (truth mask)
    was recorded with ghost fraction 0.0 and passed the ghost rule."""
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.dataset.build import build_dataset
    from mehs.preview import read_png
    from mehs.synthesis.response import ResponseCurve

    scene = make_scene("colorchecker", 16, 16, motion=True, seed=7)
    sim = simulate_bracket(scene, SensorModel(seed=3), (0.05, 0.4, 3.2), seed=0)
    folder = write_simulated_scene(sim, tmp_path / "moving", scene_id="moving")
    assert (read_png(folder / "truth" / "moved_mask.png") > 0).mean() > 0.01
    curve = ResponseCurve.linear(12).save(tmp_path / "linear.json")
    m = build_dataset([folder], tmp_path / "ds", workers=1, progress=False, response=curve,
                      ghosts="off")
    q = m["scenes"][0]["quality"]
    assert q["ghost_fraction"] is None
    assert not any("ghost" in r for r in m["scenes"][0]["reasons"])


def test_from_hs_folder_takes_upper_case_headers(tmp_path):
    """``read_envi`` reads ``B.HDR``; listing the folder with ``glob("*.hdr")`` silently
    left that cube out of the dataset."""
    from mehs.dataset.scene_list import collect_hs_cubes

    for stem in ("a", "b"):
        write_envi(tmp_path / f"{stem}.hdr", SpectralCube(np.ones((2, 2, 31), np.float32), WL31),
                   dtype=np.float32)
    for f in list(tmp_path.glob("b.*")):
        f.rename(tmp_path / ("B.HDR" if f.suffix == ".hdr" else "B" + f.suffix))
    assert sorted(s.scene_id for s in collect_hs_cubes([tmp_path])) == ["B", "a"]
    # a data file given directly finds its upper-case header too
    data = next(f for f in tmp_path.iterdir() if f.name.startswith("B.") and f.suffix != ".HDR")
    assert [s.scene_id for s in collect_hs_cubes([data])] == ["B"]


def test_data_ignore_value_samples_are_masked_not_used_as_radiance(tmp_path):
    from mehs.preview import read_png

    data = np.full((4, 5, 31), 0.5, np.float32)
    data[1, 2, 7] = -9999.0          # one dead sample
    data[3, 4, :] = -9999.0          # a pixel outside the mosaic
    write_envi(tmp_path / "in" / "c.hdr",
               SpectralCube(data, WL31, metadata={"data ignore value": "-9999"}), dtype=np.float32)
    m = build_from_hs([tmp_path / "in" / "c.hdr"], tmp_path / "ds", workers=1, progress=False)
    sc = m["scenes"][0]
    mask = read_png(tmp_path / "ds" / sc["files"]["mask"])
    assert mask[1, 2] & 4 and mask[3, 4] & 4 and not (mask[0, 0] & 4)
    assert sc["quality"]["invalid_fraction"] == 2 / 20
    from mehs.io.envi import read_envi
    hs = np.asarray(read_envi(tmp_path / "ds" / sc["files"]["hs"]).data)
    assert hs.min() >= 0          # -9999 never reached the resampled cube
