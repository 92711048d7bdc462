import numpy as np
import pytest

from mehs.cube import SpectralCube, UnsortedWavelengthsWarning
from mehs.errors import InputError


def test_unsorted_wavelengths_sorted_with_data():
    data = np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4)
    wl = [500.0, 400.0, 700.0, 600.0]
    with pytest.warns(UnsortedWavelengthsWarning):
        cube = SpectralCube(data, wl, fwhm=[5, 4, 7, 6], default_bands=(2, 0, 1))
    np.testing.assert_array_equal(cube.wavelengths, [400, 500, 600, 700])
    np.testing.assert_array_equal(cube.fwhm, [4, 5, 6, 7])
    np.testing.assert_array_equal(cube.data[..., 0], data[..., 1])
    np.testing.assert_array_equal(cube.data[..., 3], data[..., 2])
    # default bands follow their wavelengths: 700, 500, 400 nm
    assert [cube.wavelengths[b] for b in cube.default_bands] == [700, 500, 400]


@pytest.mark.parametrize("wl, msg", [
    ([400, 500, 600], "3 wavelengths given for 4 bands"),
    ([400, 500, 500, 600], "duplicate"),
    ([400, np.nan, 500, 600], "not finite"),
    (["a", "b", "c", "d"], "not numeric"),
    ([-1, 500, 550, 600], "positive"),
])
def test_bad_wavelengths(wl, msg):
    with pytest.raises(InputError, match=msg):
        SpectralCube(np.zeros((1, 1, 4)), wl, source="x.hdr")


def test_error_names_source():
    with pytest.raises(InputError, match="^scene.hdr: "):
        SpectralCube(np.zeros((1, 1, 2)), [400, 400], source="scene.hdr")
