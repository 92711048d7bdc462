"""Radiometric calibration: DN/ms → spectral radiance (see :mod:`mehs.calibration.calibrate`)."""

from mehs.calibration.calibrate import (UNIT_ABSOLUTE, UNIT_RELATIVE, UNIT_UNCALIBRATED,
                                        Calibration, calibrate_panel_relative,
                                        calibrate_source_absolute)
from mehs.calibration.spectra import Spectrum, band_average, load_spectrum

__all__ = ["Calibration", "Spectrum", "UNIT_ABSOLUTE", "UNIT_RELATIVE", "UNIT_UNCALIBRATED",
           "band_average", "calibrate_panel_relative", "calibrate_source_absolute",
           "load_spectrum"]
