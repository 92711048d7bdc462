"""Review R1: `mehs export` without --force must not replace a band-named file it did not
write (the CLI's own note: "foreign band-like files are still refused").

Truth: the file's bytes, written here with OpenEXR directly (no mehs header attributes).
"""

import numpy as np

from mehs.cli import main
from mehs.cube import SpectralCube
from mehs.io.envi import write_envi


def _foreign_exr(path):
    import OpenEXR

    px = np.full((2, 3), 7.0, np.float32)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Y": px}).write(str(path))
    return path.read_bytes()


def test_foreign_file_with_a_band_name_is_refused_not_replaced(tmp_path, capsys):
    hs = write_envi(tmp_path / "c.hdr", SpectralCube(np.ones((2, 3, 4), np.float32),
                                                     wavelengths=[450.0, 550.0, 650.0, 750.0]))
    out = tmp_path / "render"
    out.mkdir()
    before = _foreign_exr(out / "band_000.exr")     # another tool's image, same name
    assert main(["export", str(hs), "--out", str(out), "--format", "per-wavelength"]) == 2
    assert "band_000.exr" in capsys.readouterr().err
    assert (out / "band_000.exr").read_bytes() == before
    assert not (out / "band_001.exr").exists()
