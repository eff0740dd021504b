"""From the gains of the GCS-side loop to the gains written to the autopilot.

During a live tune the relay runs on the ground station: each command answers a
telemetry sample that is up to one setpoint period old and is then held for one
period, so the process the classifier identifies carries about one setpoint
period (4 ms at 250 Hz) more delay than the autopilot's own loop will see. The
identified PD is right for the GCS-side loop (it runs there during the side
tests and the hover); the written gains are re-targeted to the onboard loop:

``gains_onboard = gains_identified * PD*(model, tau - d) / PD*(model, tau)``

per gain, where ``PD*`` is the ISE-optimal PD (SPEC 2) of the identified model and
``d`` the GCS delay. The ratio keeps the identification's choice of tuning rule
and only moves it by the change the delay makes. ``d`` is never allowed to take
more than half of the identified delay (the correction is steep: over-correcting
erodes the phase margin on the true process).
"""

from __future__ import annotations

from mrft_gcs.identify import Identification
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import PD, InnerModel, inner_response

__all__ = ["onboard_gains"]


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
