"""Review R1: headers the new ENVI refusals must still take.

Truth: SPy's reader (``spectral.io.envi``) reads these headers (last value of a key wins),
and mehs's own writer wrote the first one — the reader must read back what the writer writes.
"""

import warnings

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.io.envi import read_envi, write_envi


def test_band_index_centres_written_by_mehs_read_back(tmp_path):
    # a header with 'wavelength units = Index' lists band numbers; mehs reads them as
    # 1..N and writes them back labelled Nanometers: its own file must read again
    # (whole numbers are band indices, not micrometres mislabelled — the reader's own rule)
    data = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    hp = write_envi(tmp_path / "a.hdr", SpectralCube(data, wavelengths=[1.0, 2.0, 3.0, 4.0]))
    cube = read_envi(hp)
    np.testing.assert_array_equal(np.asarray(cube.data), data)
    np.testing.assert_array_equal(cube.wavelengths, [1.0, 2.0, 3.0, 4.0])


def test_micrometres_labelled_nanometres_still_refused(tmp_path):
    from mehs.errors import FormatError

    hp = write_envi(tmp_path / "a.hdr", SpectralCube(np.ones((2, 3, 4), np.float32),
                                                     wavelengths=[400.0, 500.0, 600.0, 700.0]))
    hp.write_text(hp.read_text().replace("400.0 , 500.0 , 600.0 , 700.0", "0.4, 0.5, 0.6, 0.7"))
    with pytest.raises(FormatError, match="micrometres"):
        read_envi(hp)


@pytest.mark.parametrize("extra", [
    "interleave = BIL\n",                              # same value, other case
    "wavelength = {400, 500.00, 6.0e2, 700}\n",        # same numbers, other spelling
    "wavelength units = nanometers\n",
])
def test_key_repeated_with_the_same_meaning_is_read(tmp_path, extra):
    import spectral.io.envi as envi

    data = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    hp = write_envi(tmp_path / "a.hdr", SpectralCube(data, wavelengths=[400.0, 500.0, 600.0, 700.0]))
    hp.write_text(hp.read_text() + extra)
    ref = envi.open(str(hp), str(tmp_path / "a.raw")).load()   # SPy reads it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cube = read_envi(hp)
    np.testing.assert_array_equal(np.asarray(cube.data), np.asarray(ref))
    np.testing.assert_array_equal(cube.wavelengths, [400.0, 500.0, 600.0, 700.0])
