"""Render scores against published values (no Mitsuba needed)."""

import numpy as np
import pytest

from mehs.render.compare import (delta_E2000, difference_image, relative_error, score,
                                 spectral_angle_deg, white_Y)
from mehs.rgb import XYZ_to_linear_sRGB

# Sharma, Wu & Dalal 2005, Table 1: CIELAB pairs and their CIEDE2000
SHARMA = [((50.0, 2.6772, -79.7751), (50.0, 0.0, -82.7485), 2.0425),
          ((50.0, -1.0, 2.0), (50.0, 0.0, 0.0), 2.3669),
          ((50.0, 2.5, 0.0), (73.0, 25.0, -18.0), 27.1492),
          ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644)]


def test_delta_E2000_reproduces_sharma_2005_through_the_rgb_path():
    import colour

    wp = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    a = np.array([[p[0] for p in SHARMA]])
    b = np.array([[p[1] for p in SHARMA]])
    to_rgb = lambda lab: XYZ_to_linear_sRGB(colour.Lab_to_XYZ(lab, wp), clip_negative=False)  # noqa: E731
    de = delta_E2000(to_rgb(a), to_rgb(b), y_white=1.0)
    assert de[0] == pytest.approx([p[2] for p in SHARMA], abs=1e-3)


def test_relative_error_difference_and_angle():
    ref = np.full((2, 3, 3), 2.0, np.float32)
    img = ref.copy()
    img[0, 0] = [3.0, 2.0, 1.0]
    assert relative_error(img, ref) == pytest.approx(2.0 / 36.0)
    assert np.allclose(difference_image(img, ref)[0, 0], [5.0, 0.0, 5.0])
    assert white_Y(ref) > 0
    s = score(ref, ref)
    assert s["mean_delta_E2000"] == pytest.approx(0.0, abs=1e-9) and s["relative_error"] == 0.0
    assert spectral_angle_deg(np.array([1.0, 0.0]), np.array([1.0, 1.0])) == pytest.approx(45.0)
    assert np.isnan(spectral_angle_deg(np.zeros(3), np.ones(3)))
