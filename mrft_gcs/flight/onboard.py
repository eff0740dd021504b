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

``d`` (:func:`gcs_delay_s`) is half a setpoint period: telemetry and the stream's
ticks are not synchronised, so a sample waits on average half a period for the
command that answers it; the rest (the link both ways, the vehicle taking the
command) is left in the written gains, which errs on the side of margin. Measured
live (qdrone, racer250, 3 seeds each, quiet box): re-targeting by a whole period
(4 ms at 250 Hz) left the written roll/pitch gains aggressive: PM on the true process
below 15 deg (11.1-14.8) in 6 of 9 completed tunes, J down to -9.4 %; by half a
period, PM 18.6-22.8 deg and J -2.0 to +4.6 % in 6 of 6. Racer250's roll was identified with 6.4 ms of delay against a true
8 ms plus the GCS's 2.5-3 ms: the identification does not resolve all of the GCS
delay, so removing a whole period took delay that had never been identified.
"""

from __future__ import annotations

from mrft_gcs.identify import Identification
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response

__all__ = ["onboard_gains", "gcs_delay_s"]


def gcs_delay_s(setpoint_period_s: float) -> float:
    """Delay re-targeted out of the identified inner loops for a GCS relay (s).

    >>> gcs_delay_s(0.004)
    0.002
    """
    return 0.5 * setpoint_period_s


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
