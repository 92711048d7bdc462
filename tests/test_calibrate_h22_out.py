"""mehs calibrate never writes into a raw capture (as every other writing command)."""

from mehs.cli import main


def test_calibration_file_inside_the_raw_capture_is_refused(tmp_path, capsys):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    sim = simulate_bracket(make_scene("colorchecker", 8, 8, seed=1), SensorModel(seed=2),
                           (0.05, 0.4), seed=0)
    folder = write_simulated_scene(sim, tmp_path / "s", scene_id="s")
    before = sorted(p.relative_to(folder) for p in folder.rglob("*"))
    code = main(["calibrate", str(folder), "--panel", "0.9", "--illuminant", "D65",
                 "--out", str(folder / "cal.json")])
    assert code == 2
    assert "raw capture" in capsys.readouterr().err
    assert sorted(p.relative_to(folder) for p in folder.rglob("*")) == before
