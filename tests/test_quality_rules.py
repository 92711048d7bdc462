"""Audit of the pass/fail rules (mehs.dataset.quality.judge) against their documented meaning."""

import math

import pytest

from mehs.dataset.quality import QualityRules, judge
from mehs.errors import InputError


@pytest.mark.parametrize("key", ["ghost_fraction", "saturated_fraction", "invalid_fraction",
                                 "dynamic_range_stops", "response_uncertainty"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_nan_or_infinite_figure_fails_instead_of_passing_every_rule(key, bad):
    status, reasons = judge({key: bad})
    assert status == "fail"
    assert any("not a finite number" in r for r in reasons), reasons


def test_a_failing_value_is_shown_with_the_digits_that_tell_it_from_the_threshold():
    status, reasons = judge({"dynamic_range_stops": 3.9996, "ghost_fraction": 0.010004})
    assert status == "fail"
    assert "ghost fraction 0.010004 > 0.01" in reasons
    assert "dynamic range 3.9996 stops < 4" in reasons
    # ordinary values keep their short form
    assert judge({"dynamic_range_stops": 3.5})[1] == ["dynamic range 3.5 stops < 4"]
    assert judge({"saturated_fraction": 0.0071614583})[1] == \
        ["saturated-in-all fraction 0.00716 > 0.005"]


def test_the_response_reason_puts_the_value_beside_its_name():
    _, reasons = judge({"response_uncertainty": 0.05})
    assert reasons == ["response curve undetermined: uncertainty 0.05 > 0.02 "
                       "(use a ladder curve, --response)"]


def test_a_dynamic_range_rule_of_none_is_off_not_a_type_error():
    rules = QualityRules(min_dynamic_range_stops=None)  # accepted by the rules' own check
    assert judge({"dynamic_range_stops": 1.0}, rules) == ("pass", [])


@pytest.mark.parametrize("bad", [math.nan, "2", 0, 1.5, True])
def test_min_exposures_must_be_a_whole_number(bad):
    with pytest.raises(InputError, match="min_exposures"):
        QualityRules(min_exposures=bad)


def test_min_exposures_given_as_a_float_is_an_int():
    rules = QualityRules(min_exposures=3.0)
    assert rules.min_exposures == 3 and isinstance(rules.min_exposures, int)
    assert judge({"n_exposures": 2}, rules)[1] == ["only 2 complete exposure(s) < 3"]


def test_thresholds_are_strict_and_unknown_figures_are_not_judged():
    r = QualityRules()
    at = {"ghost_fraction": r.max_ghost_fraction, "saturated_fraction": r.max_saturated_fraction,
          "invalid_fraction": r.max_invalid_fraction,
          "dynamic_range_stops": r.min_dynamic_range_stops, "n_exposures": r.min_exposures}
    assert judge(at, r) == ("pass", [])
    assert judge({k: None for k in at}, r) == ("pass", [])


def test_a_curve_undetermined_by_exposure_consistency_fails_despite_a_small_uncertainty():
    # the check's split-half / prior figure is small, but its exposure-consistency test
    # marked the curve undetermined (a biased curve): the scene must not pass
    status, reasons = judge({"response_uncertainty": 0.018, "response_undetermined": True})
    assert status == "fail" and any("undetermined" in r for r in reasons), reasons
    assert judge({"response_uncertainty": 0.018, "response_undetermined": False}) == ("pass", [])
