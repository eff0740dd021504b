"""Safety limits (SPEC 5) checked on every tick."""

import pytest

from mrft_gcs.errors import SafetyAbort
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.safety import LimitExceeded, SafetyMonitor
from mrft_gcs.profiles import SafetyLimits


def state(t=1.0, roll=0.0, x=0.0, y=0.0, z=1.0):
    return FlightState(t, roll, 0.0, 0.0, 0, 0, 0, t, x, y, z, 0, 0, 0)


@pytest.mark.parametrize("s, word", [
    (state(roll=0.7), "tilt"),
    (state(z=6.0), "altitude"),
    (state(x=4.0, y=4.0), "from take-off"),
    (state(t=61.5), "running for"),
])
def test_each_limit_aborts(s, word):
    m = SafetyMonitor(SafetyLimits(), (0.0, 0.0, 0.0), 0.0)
    assert m.violation(state()) is None
    with pytest.raises(LimitExceeded, match=word) as err:
        m.check(s)
    assert isinstance(err.value, SafetyAbort) and err.value.exit_code == 5
    assert "landing commanded" in str(err.value)


def test_overrides_and_origin():
    lim = SafetyLimits().with_overrides(max_tilt_deg=10.0, max_distance_m=None)
    assert lim.max_tilt_deg == 10.0 and lim.max_distance_m == 5.0
    m = SafetyMonitor(lim, (10.0, 0.0, 2.0), 0.0)
    assert m.violation(state(x=12.0, z=3.0)) is None  # distances from the take-off point
    assert "tilt" in m.violation(state(roll=0.2))
    assert m.max_tilt_seen_deg > 11
    assert m.violation(state(t=100.0, x=10.0), duration=False) is None
