"""``engine.core.checks.check_range``: the range check of config numbers (one-line errors naming the option)."""
import numpy as np
import pytest

from engine.core.checks import check_range
from engine.core.errors import InputError


@pytest.mark.parametrize("value, kwargs, expected", [
    (1, dict(low=1, integer=True), 1),
    (np.int64(7), dict(low=1, integer=True), 7),
    (0, dict(low=0, high=1), 0.0),
    (1, dict(low=0, high=1), 1.0),
    (np.float32(0.5), dict(low=0, high=1, low_open=True, high_open=True), 0.5),
    (-3.5, dict(high=-1), -3.5),
    (12.0, dict(), 12.0),
])
def test_values_inside_the_interval_come_back_as_int_or_float(value, kwargs, expected):
    out = check_range(value, "x", **kwargs)
    assert out == expected and type(out) is (int if kwargs.get("integer") else float)


@pytest.mark.parametrize("value, kwargs, message", [
    (0, dict(low=1, integer=True), "must be an integer >= 1, got 0"),
    (2.0, dict(low=1, integer=True), "must be an integer >= 1, got 2.0"),
    (True, dict(low=0, integer=True), "must be an integer >= 0, got True"),
    ("3", dict(low=0, integer=True), "must be an integer >= 0, got '3'"),
    (0, dict(low=0, low_open=True), "must be > 0, got 0"),
    (1, dict(low=0, high=1, high_open=True), "must be in [0, 1), got 1"),
    (1.5, dict(low=0, high=1), "must be in [0, 1], got 1.5"),
    (0.0, dict(low=0, high=1, low_open=True), "must be in (0, 1], got 0.0"),
    (5, dict(high=4), "must be <= 4, got 5"),
    (float("nan"), dict(low=0), "must be >= 0, got nan"),
    (float("inf"), dict(low=0), "must be >= 0, got inf"),
    (None, dict(), "must be a finite number, got None"),
    (False, dict(low=0), "must be >= 0, got False"),
])
def test_values_outside_it_raise_one_line_naming_the_field(value, kwargs, message):
    with pytest.raises(InputError) as err:
        check_range(value, "priors.flow.rays", **kwargs)
    assert str(err.value) == f"field 'priors.flow.rays': {message}"


def test_config_validators_use_it_with_the_option_the_user_typed():
    from models.fields.priors.flow import SparseFlowPrior
    from models.fields.dynamic.model import MotionConfig

    with pytest.raises(InputError, match=r"field 'priors.flow.min_coherent': must be <= neighbours \(6\), got 7"):
        SparseFlowPrior(min_coherent=7).validate()
    with pytest.raises(InputError, match=r"field 'priors.flow.fade_to': must be in \[0, 1\], got 1.5"):
        SparseFlowPrior(fade_to=1.5).validate()
    with pytest.raises(InputError, match=r"field 'field.motion.max_flow': must be > 0, got 0.0"):
        MotionConfig(max_flow=0.0).validate()
