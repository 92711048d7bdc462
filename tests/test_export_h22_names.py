"""Exports stage their files under hidden temporary names: what a user reads in a warning
or an error must name the file they will find, not the temporary one."""

import warnings

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.export import export_per_wavelength
from mehs.io.exr import HalfFloatUnderflowWarning


def _dim_cube():
    wl = np.arange(400.0, 431.0, 10.0)
    data = np.full((4, 5, wl.size), 1e-9, dtype=np.float32)    # below half's 2^-25
    return SpectralCube(data, wl)


def test_half_underflow_warning_names_the_band_file(tmp_path):
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        paths = export_per_wavelength(_dim_cube(), tmp_path / "exr", half=True)
    texts = [str(w.message) for w in seen if issubclass(w.category, HalfFloatUnderflowWarning)]
    assert texts and all(".part" not in t for t in texts), texts
    assert str(paths[0]) in texts[0]


def test_spectral_file_error_names_the_final_file(tmp_path):
    from mehs.io.exr_spectral import write_exr_spectral

    target = tmp_path / "band.exr"
    data = np.ones((2, 3, 4), np.float32)
    data[1, 1, 2] = np.nan
    tmp = tmp_path / ".band.exr.123.part.exr"
    with pytest.raises(InputError) as err:
        write_exr_spectral(tmp, data, [400.0, 410, 420, 430], name=target)
    assert str(err.value.path) == str(target) and not tmp.exists()
    with pytest.raises(InputError) as err:      # the array-level checks too
        write_exr_spectral(tmp, data[:, :, :3], [400.0, 410, 420, 430], name=target)
    assert str(err.value.path) == str(target)
