"""Rate limit or saturation from two relay amplitudes, before the larger one is flown long.

Under a relay a linear loop (delays, lags, filters included) oscillates at a period
that does not depend on the relay amplitude ``h``, with an amplitude proportional
to it. A rate limit on the input ramps each switch over ``2 h / rate``: its lag grows
with ``h``, so a larger relay gives a longer period and an amplitude that grows
faster than ``h`` (the tilt a larger relay reaches is underestimated by scaling, and
can flip a vehicle). A saturation caps the input: the amplitude grows slower than
``h``, the period barely moves. An identified model absorbs either into its lag or
gain at one amplitude, so the cycle shape at one amplitude hides them; the change
between two amplitudes does not.

:func:`amplitude_check` compares a cycle at ``h1`` with one at ``h2`` (e.g. a tune's
first period at a small relay and the first cycle after sizing it up) and returns an
:class:`AmplitudeCheck`. Measured on the bundled SITL (roll, beta -0.7, h 0.04 then
0.12, noise-free): linear effects (none, 12 Hz sensor filter, 20 ms delay) period and
amplitude ratios 1.000; torque rate limit 8 / 4 / 2 per s: period x1.18 / 1.32 / 1.47,
amplitude x1.40 / 1.72 / 2.05 of the linear scaling; motor saturation at 0.5:
amplitude x0.88, period x1.00.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["AmplitudeCheck", "amplitude_check", "PERIOD_TOL", "AMPLITUDE_TOL"]

#: Relative period change between the two amplitudes above which the lag grows with the
#: amplitude (a rate limit); sampling and noise move a steady period by a few %.
PERIOD_TOL = 0.08
#: Relative shortfall of the amplitude against linear scaling that counts as saturation.
AMPLITUDE_TOL = 0.08


@dataclass(frozen=True)
class AmplitudeCheck:
    """What two relay amplitudes say about the input path.

    Attributes
    ----------
    period_ratio : float
        Period at ``h2`` over period at ``h1``.
    gain_ratio : float
        Amplitude at ``h2`` over the amplitude linear scaling predicts (``a1 h2 / h1``).
    verdict : str
        ``"linear"``, ``"rate_limit"`` (lag grows with the amplitude) or ``"saturation"``
        (amplitude short of linear scaling, period unchanged).
    """

    period_ratio: float
    gain_ratio: float
    verdict: str

    def note(self) -> str:
        """One line for a report."""
        if self.verdict == "rate_limit":
            return (f"the cycle lags more at the larger relay (period x{self.period_ratio:.2f}, "
                    f"amplitude x{self.gain_ratio:.2f} of linear scaling): a rate limit on "
                    f"the input; a larger relay would swing further than scaling predicts")
        if self.verdict == "saturation":
            return (f"the amplitude grows slower than the relay (x{self.gain_ratio:.2f} of "
                    f"linear scaling, period x{self.period_ratio:.2f}): the input saturates")
        return (f"linear between the two relay amplitudes (period x{self.period_ratio:.2f}, "
                f"amplitude x{self.gain_ratio:.2f} of linear scaling)")


def amplitude_check(period1_s: float, amplitude1: float, h1: float, period2_s: float,
                    amplitude2: float, h2: float) -> AmplitudeCheck:
    """Compare relay cycles at two amplitudes ``h1 < h2`` (input units).

    Parameters
    ----------
    period1_s, amplitude1, h1 : float
        Period (s), half peak-to-peak amplitude (output units) and relay amplitude of the
        first cycle(s).
    period2_s, amplitude2, h2 : float
        The same at the second relay amplitude.

    Raises
    ------
    ValueError
        Non-positive inputs or ``h2 <= h1``.
    """
    vals = (period1_s, amplitude1, h1, period2_s, amplitude2, h2)
    if min(vals) <= 0:
        raise ValueError("periods, amplitudes and relay amplitudes must be positive")
    if h2 <= h1:
        raise ValueError("the second relay amplitude must be the larger")
    pr = period2_s / period1_s
    gr = amplitude2 / (amplitude1 * h2 / h1)
    if pr > 1 + PERIOD_TOL:
        verdict = "rate_limit"
    elif gr < 1 - AMPLITUDE_TOL:
        verdict = "saturation"
    else:
        verdict = "linear"
    return AmplitudeCheck(pr, gr, verdict)
