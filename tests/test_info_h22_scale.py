"""mehs info names a bad 'reflectance scale factor' as read_envi does, instead of a traceback
(abc) or printing it (0, which would divide every value by zero)."""

import numpy as np
import pytest

from mehs.cli import main
from mehs.cube import SpectralCube
from mehs.io.envi import write_envi


@pytest.mark.parametrize("value", ["abc", "0", "nan"])
def test_bad_reflectance_scale_factor_is_one_named_error(tmp_path, capsys, value):
    hdr = write_envi(tmp_path / "c.hdr", SpectralCube(np.ones((2, 3, 4), np.int16) * 500,
                                                      np.array([400.0, 500, 600, 700])))
    text = hdr.read_text()
    hdr.write_text(text.rstrip("\n") + f"\nreflectance scale factor = {value}\n")
    assert main(["info", str(hdr)]) == 2
    err = capsys.readouterr().err
    assert "reflectance scale factor" in err and str(hdr) in err


def test_good_reflectance_scale_factor_is_applied(tmp_path, capsys):
    hdr = write_envi(tmp_path / "c.hdr", SpectralCube(np.ones((2, 3, 4), np.int16) * 500,
                                                      np.array([400.0, 500, 600, 700])))
    hdr.write_text(hdr.read_text().rstrip("\n") + "\nreflectance scale factor = 1000\n")
    assert main(["info", str(hdr), "--json"]) == 0
    out = capsys.readouterr().out
    assert '"reflectance_scale_factor": 1000.0' in out
