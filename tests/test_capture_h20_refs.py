"""Dark and white references of a written scene are the lines the sensor read, so the
bracket a reader loads carries the references' exact mean, not a mean rounded to whole DN."""

import numpy as np

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket, write_simulated_scene
from mehs.io.specim import read_specim_folder
from mehs.synthesis.bracket import load_bracket


def test_written_references_average_to_the_sensor_mean(tmp_path):
    scene = make_scene("colorchecker", lines=24, samples=20, seed=2)
    sim = simulate_bracket(scene, SensorModel(seed=5), [2.0, 8.0], dark_lines=16)
    out = write_simulated_scene(sim, tmp_path / "s")
    b = load_bracket(out, verify="none")
    for k in range(2):
        # the truth here: the simulator's own shutter-closed lines, averaged in float64
        truth = sim.dark_frames[k].mean(axis=0, dtype=np.float64)
        np.testing.assert_allclose(b.darks[k], truth, rtol=0, atol=1e-4)
        folder = out / "exposures" / sorted(p.name for p in (out / "exposures").iterdir())[k]
        cap = read_specim_folder(folder)
        assert cap.darkref.data.shape[0] == 16 and cap.darkref.data.dtype == np.uint16
    wtruth = sim.white_frames[0].mean(axis=0, dtype=np.float64)
    np.testing.assert_allclose(b.white[0], wtruth, rtol=0, atol=1e-3)
