"""The hold-bias calibration (gesture.eval.hold_bias): repeat rates, the choice of bias, bad inputs, and a short run
of the real default agent on a generated validation session."""

from __future__ import annotations

import numpy as np
import pytest

from ecas.core.paths import DEFAULT_CONFIG
from gesture.eval import hold_bias


def test_repeat_rates_count_steps_whose_code_equals_the_previous_one_per_level():
    tokens = np.array([[1, 5], [1, 6], [1, 6], [2, 7], [2, 7]])  # (T=5, L=2)
    np.testing.assert_allclose(hold_bias.repeat_rates(tokens), [3 / 4, 2 / 4])
    with pytest.raises(ValueError, match="tokens: need at least 2 steps"):
        hold_bias.repeat_rates(tokens[:1])


def test_closest_bias_matches_only_the_named_levels():
    target = np.array([0.6, 0.3, 0.1])
    rates = {0.0: np.array([0.4, 0.3, 0.1]), 0.5: np.array([0.58, 0.25, 0.5]), 1.0: np.array([0.7, 0.4, 0.1])}
    assert hold_bias.closest_bias(rates, target, [0, 1]) == 0.5
    assert hold_bias.closest_bias(rates, target, [2]) in (0.0, 1.0)


def test_cli_refuses_bad_options_by_name(capsys):
    with pytest.raises(SystemExit):
        hold_bias.main(["--sessions", "0"])
    assert "--sessions must be >= 1" in capsys.readouterr().err


def test_a_larger_bias_repeats_more_often_on_a_validation_session(tmp_path):
    report = hold_bias.measure(
        DEFAULT_CONFIG, [0.0, 3.0], tmp_path / "validation", 1, 6.0, seed=0, progress=lambda msg: None
    )
    assert report["sessions"] == ["31_synth_0_1_1"] and report["seconds"] == pytest.approx(6.0)
    level0 = {b: rates[0] for b, rates in report["by_bias"].items()}
    assert level0["3.0"] > level0["0.0"] + 0.2
    assert 0 < report["tokens"][0] < 1 and report["closest"] in (0.0, 3.0)
    with pytest.raises(ValueError, match="levels: must be token levels"):
        hold_bias.measure(
            DEFAULT_CONFIG, [0.0], tmp_path / "validation", 1, 12.0, seed=0, levels=[99], progress=lambda msg: None
        )
