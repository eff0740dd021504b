"""The side (x, y) relays: the bounding relay while the inner tests run, then MRFT on x and y.

Until an axis's own test starts, the bounding relay of eq. 22 keeps it near the take-off
point. Once its attitude loop can take tilt commands, a soft PD brings it to rest; its relay
starts when :meth:`SideRelays.start` is given the side-motion relay settings (after roll,
pitch and altitude are done). x is driven by ``-pitch``, y by ``+roll``: the relays and PDs
output that tilt command in rad, along the take-off heading's forward and right axes.
"""

from __future__ import annotations

import numpy as np

from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.flight.phases.state import SIDE_INNER, LoopState, LoopTest
from mrft_gcs.identify import RelaySettings
from mrft_gcs.loops import SIDE_LOOPS, Loop
from mrft_gcs.profiles import Actuation
from mrft_gcs.relay import MRFT, BoundingRelay

__all__ = ["SideRelays", "tilt_on"]


class SideRelays:
    """x and y from the take-off command on (tilt commands in rad).

    Parameters
    ----------
    shared : Shared
        The sequence's shared state (filtered position, take-off point, loops).
    """

    def __init__(self, shared: Shared) -> None:
        self.sh = shared
        to = shared.config.takeoff
        self.bounding = BoundingRelay(to.eps1_m, to.eps2_m, to.h_o1_rad, to.h_o2_rad, n=2)

    def ready(self) -> list[Loop]:
        """Side loops not started, once both attitude loops are done.

        Altitude must be done too: its relay swings the thrust by +-h (about a quarter of
        hover), which modulates the horizontal force of a tilt and breaks the side cycles.
        Scaling the tilt commands by hover / thrust does not undo it (it lags by the
        attitude loop's response).
        """
        loops = self.sh.loops
        done = (LoopState.TUNED, LoopState.LEFT_ALONE)
        if loops[Loop.ALTITUDE].state not in done:
            return []
        if not self.sh.inner_done:
            # both attitude loops first: a side relay tilts its axis, which can throw the
            # other attitude loop's relay, still running, into a slow drifting cycle
            return []
        return [lp for lp in SIDE_INNER if loops[lp].state is LoopState.WAITING]

    def start(self, settings: dict[Loop, RelaySettings], now: FlightState | None) -> None:
        """Start the x/y relays that are ready (see :meth:`ready`); each settles first."""
        ready = self.ready()
        for lp, rs in settings.items():
            t = self.sh.loops[lp]
            if lp not in ready:
                continue
            t.beta, t.h = rs.beta, max(rs.h, self.sh.config.h_side_min)
            t.band = self.sh.noise_band(lp)
            t.relay = MRFT(t.beta, t.h, band=t.band)
            t.state = LoopState.RELAY
            t.settling = True
            t.center = self.sh.xy_f[0 if lp is Loop.X else 1]
            t.t_relay_start_s = max(now.t_att_s, now.t_pos_s) if now else float("nan")

    def step(self, s: FlightState, new: bool) -> tuple[float, float]:
        """Tilt commands (x: ``-pitch``, y: ``+roll``; rad) for this tick; ``s`` in the
        take-off heading frame, ``new``: a new position sample."""
        sh = self.sh
        cfg = sh.config
        ex = sh.origin[0] - s.x_m
        ey = sh.origin[1] - s.y_m
        tx, ty = sh.loops[Loop.X], sh.loops[Loop.Y]
        xf, yf = sh.xy_f
        bb = (0.0, 0.0)
        held = (LoopState.WAITING, LoopState.LEFT_ALONE)  # no test of their own (yet)
        if tx.state in held or ty.state in held:
            # the bounding relay keeps an axis near the take-off point until its test starts
            b2 = self.bounding.step(np.array([ex, ey]))
            bb = (float(b2[0]), float(b2[1]))
        out = []
        for t, pos, vel, o, pf, b in ((tx, s.x_m, s.vx_m_s, sh.origin[0], xf, bb[0]),
                                      (ty, s.y_m, s.vy_m_s, sh.origin[1], yf, bb[1])):
            if t.state in held and self._attitude_ready(t.loop):
                # its attitude loop is tuned: bring the axis to rest already (the soft settle
                # PD about where it was then), so that its relay can start as soon as the
                # altitude test ends instead of settling only then; an axis left alone
                # (not requested) is held there for the rest of the tune
                if not t.presettle:
                    t.presettle, t.center = True, pf
                u = self._settle(t.center - pf, vel)
            elif t.state in held:
                u = b
            elif t.pd is not None:
                # hold where the relay oscillated: a step back to the take-off point would
                # disturb the other axis while its test still runs
                u = t.pd.step(t.center if t.identification is not None else o, pos, vel)
            elif t.relay is not None and t.settling:
                u = self._settle(t.center - pf, vel)
                if (abs(vel) < cfg.settle_speed_m_s or
                        s.t_pos_s - t.t_relay_start_s > cfg.settle_max_s):
                    t.settling, t.center = False, pf
                    if cfg.side_start_high:
                        # the relay starts high: it switches down as soon as the axis leaves
                        # the noise band, and the cycle detector (which learns the relay's
                        # levels from the data) counts the rise that follows. Started low,
                        # as a first error just under zero did, its first rise came before
                        # the detector knew the levels and the first cycle began a whole
                        # period after the start
                        t.relay.reset()
                        t.relay.state[:] = 1.0
            elif t.relay is not None:
                before = float(t.relay.state[0])
                u = float(t.relay.step(t.center - pf)[0])
                sh.watch(t, t.relay, t.center - pf, before)
                sh.feed(t, s.t_pos_s, u, pf, new)
            else:
                u = 0.0
            t.u = u
            out.append(u)
        return out[0], out[1]

    def record_tilt(self, s: FlightState, c: float, n: float) -> None:
        """On a new attitude sample: the measured tilt along each running relay's axis.

        ``c``, ``n``: cosine and sine of the heading's departure from the take-off heading
        (the rotation the tilt commands went through onto roll and pitch).
        """
        for lp, tilt in ((Loop.X, c * -s.pitch_rad - n * s.roll_rad),
                         (Loop.Y, c * s.roll_rad - n * s.pitch_rad)):
            t = self.sh.loops[lp]
            if t.relay is not None and not t.settling:
                t.tilt.append((s.t_att_s, tilt))

    def _attitude_ready(self, loop: Loop) -> bool:
        """The attitude loop behind side ``loop`` can take a position PD's tilt commands.

        Torque path: once the GCS runs its identified PD. Attitude path: the autopilot's
        own loop is there from the start, but the bounding relay (eq. 22) keeps the axis
        until the altitude test is over, as on the torque path.
        """
        if self.sh.config.actuation is Actuation.ATTITUDE:
            return self.sh.loops[Loop.ALTITUDE].state in (LoopState.TUNED,
                                                          LoopState.LEFT_ALONE)
        return self.sh.loops[SIDE_INNER[loop]].pd is not None

    def _settle(self, e: float, vel: float) -> float:
        """The soft PD that brings a side axis to rest (tilt command, rad, clipped)."""
        kp, kd = self.sh.config.settle_pd
        lim = self.sh.config.settle_max_tilt_rad
        return min(lim, max(-lim, kp * e - kd * vel))


def tilt_on(t: LoopTest, ts: np.ndarray) -> np.ndarray | None:
    """The side axis' measured tilt at the times ``ts`` (None if it does not cover them)."""
    if t.loop not in SIDE_LOOPS or len(t.tilt) < 2:
        return None
    tt, tv = np.array(t.tilt).T
    if tt[0] > ts[0] + 0.02 or tt[-1] < ts[-1] - 0.02:  # ATTITUDE and LOCAL_POSITION_NED
        return None  # samples need not coincide, but must cover the cycles
    return np.interp(ts, tt, tv)
