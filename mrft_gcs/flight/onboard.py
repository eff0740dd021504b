"""From the gains of the GCS-side loop to the gains written to the autopilot.

During a live tune the relay runs on the ground station: each command answers a
telemetry sample and acts on the vehicle some time after it, so the process the
identification sees carries more delay than the autopilot's own loop will. The
identified PD is right for the GCS-side loop (it runs there during the side
tests and the hover); the written gains are re-targeted to the onboard loop:

``gains_onboard = gains_identified * PD*(model, tau - d) / PD*(model, tau)``

per gain, where ``PD*`` is the ISE-optimal PD (SPEC 2) of the identified model and
``d`` the GCS delay. The ratio keeps the identification's choice of tuning rule
and only moves it by the change the delay makes. ``d`` is never allowed to take
more than half of the identified delay (the correction is steep: over-correcting
erodes the phase margin on the true process).

``d`` is measured (:func:`command_delay_s`): over the identified cycles, how old
each telemetry sample was when the command answering it left, counted from the
earliest the link has delivered a sample (the session's smallest receive-minus-vehicle
time, as the .tlog reader places commands on the vehicle clock, so dry-run measures the
same on the session's log; a vehicle clock drifting 20 ppm against the ground station's
moves it by 0.2 ms per 10 s of session). Telemetry and the stream's ticks are not
synchronised: at 250 Hz both, their phase is fixed for a session at whatever it
happened to be, so this age is anywhere from 0 to 4 ms from one tune to the next
(measured live: session means 1.4-4.9 ms), plus the reader's and the stream's
lateness on a loaded machine. The link's smallest latency both ways and the vehicle
taking the command are not measured and stay in the written gains, on the side of
margin. Without a measurement (too few samples), ``d`` is half a setpoint period
(:func:`gcs_delay_s`), the mean of an unsynchronised wait.

Why it matters: racer250's roll (8 ms of delay) loses about 3.5 % of J per millisecond
of GCS delay left in its gains. Re-targeting by a fixed half period left the written
gains from 5 % aggressive to 9 % cautious with the session's phase (live, 3 seeds);
earlier, a fixed whole period (4 ms) left them aggressive: PM on the true process below
15 deg in 6 of 9 tunes (11.1-14.8). Racer250's roll was once identified with 6.4 ms of
delay against a true 8 ms plus the GCS's 2.5-3 ms: the identification does not resolve
all of the GCS delay, hence the cap below.
"""

from __future__ import annotations

import numpy as np

from mrft_gcs.identify import Identification
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response

__all__ = ["onboard_gains", "gcs_delay_s", "command_delay_s", "retarget_delay_s"]


def gcs_delay_s(setpoint_period_s: float) -> float:
    """Delay re-targeted out of the identified inner loops for a GCS relay (s).

    >>> gcs_delay_s(0.004)
    0.002
    """
    return 0.5 * setpoint_period_s


#: ages over this many setpoint periods are a stall, not the loop's steady delay: clipped
AGE_CLIP_PERIODS = 3.0
#: fewer aged samples than this in a window: no measurement
MIN_AGED_SAMPLES = 20


def command_delay_s(ages_s, setpoint_period_s: float) -> float:
    """The GCS delay of a relay loop from its samples' ages (s; NaN: too few).

    The mean age, each clipped to :data:`AGE_CLIP_PERIODS` setpoint periods.

    >>> command_delay_s([0.002] * 24 + [0.2], 0.004)  # the stall counts as 12 ms
    0.0024
    >>> command_delay_s([0.002] * 5, 0.004)
    nan
    """
    a = np.asarray(ages_s, dtype=float)
    a = a[np.isfinite(a)]
    if a.size < MIN_AGED_SAMPLES:
        return float("nan")
    return round(float(np.mean(np.clip(a, 0.0, AGE_CLIP_PERIODS * setpoint_period_s))), 9)


def retarget_delay_s(ages_s, setpoint_period_s: float) -> tuple[float, bool]:
    """The delay to re-target out of a relay loop's written gains (s), and whether it was
    measured: :func:`command_delay_s` of the ages, else half a period (:func:`gcs_delay_s`).

    >>> retarget_delay_s([], 0.004)
    (0.002, False)
    """
    d = command_delay_s(ages_s, setpoint_period_s)
    return (d, True) if np.isfinite(d) else (gcs_delay_s(setpoint_period_s), False)


def onboard_gains(ident: Identification, delay_s: float) -> PD:
    """Gains for the onboard loop of an identified inner loop, ``delay_s`` less delay.

    Side loops (and ``delay_s <= 0``) keep the identified gains.

    >>> from mrft_gcs.loops import LoopKind
    >>> m = InnerModel(K=40.0, T_prop=0.02, T1=0.25, tau=0.02)
    >>> i = Identification(LoopKind.ATTITUDE, m, 0, 1.0, -0.8, 0.1, 0.25, 0.03, PD(1.0, 0.1))
    >>> g = onboard_gains(i, 0.004)
    >>> g.Kc > 1.0 and g.Kd > 0.1
    True
    """
    m = ident.model
    if not isinstance(m, InnerModel) or not delay_s > 0:
        return ident.gains
    d = min(delay_s, 0.5 * m.tau)

    def best(tau: float) -> PD:
        w = frequency_grid(m.T_prop, m.T1, tau)
        return optimal_pd(inner_response(m.K, m.T_prop, m.T1, tau, w)[0], w).pd

    p0, p1 = best(m.tau), best(m.tau - d)
    return PD(ident.gains.Kc * p1.Kc / p0.Kc, ident.gains.Kd * p1.Kd / p0.Kd)
