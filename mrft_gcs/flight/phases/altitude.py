"""The altitude relay: the climb, then MRFT on altitude about the height the climb held.

The take-off controller (:mod:`mrft_gcs.flight.takeoff`, eq. 21) flies the climb and runs the
altitude relay once the vehicle holds its set point; this phase feeds the relay's cycles to
the watcher, starts a lopsided relay over, and flies the identified PD afterwards.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from mrft_gcs.errors import IdentificationError
from mrft_gcs.features import crosses_setpoint, rising_switches
from mrft_gcs.flight.controllers import FlightState
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.flight.phases.state import LoopState, LoopTest
from mrft_gcs.identify import RelaySettings
from mrft_gcs.loops import Loop
from mrft_gcs.relay import MRFT

__all__ = ["AltitudeRelay"]


class AltitudeRelay:
    """The altitude loop from the take-off command on.

    Parameters
    ----------
    shared : Shared
        The sequence's shared state (its take-off controller runs the relay).
    settings : RelaySettings
        MRFT beta and h for altitude (normalised thrust).
    """

    def __init__(self, shared: Shared, settings: RelaySettings) -> None:
        self.sh = shared
        alt = shared.loops[Loop.ALTITUDE]
        alt.beta, alt.h = settings.beta, settings.h
        #: whether each of the relay's last switches came before its threshold armed
        self._unarmed: deque[bool] = deque(maxlen=4)

    def start(self, t_s: float) -> None:
        """Take-off command at ``t_s``: the relay (inside the climb) counts from now."""
        alt = self.sh.loops[Loop.ALTITUDE]
        alt.state, alt.t_relay_start_s = LoopState.RELAY, t_s
        alt.band = self.sh.takeoff.band_m = self.sh.noise_band(Loop.ALTITUDE)
        cfg = self.sh.config
        arm = alt.band / (1 + alt.beta)  # the smallest half-cycle that arms a switch (m)
        if cfg.runaway_factor * arm > cfg.runaway_floor_alt_max_m:
            # its cycles would have to swing past what the run-away guard lets through (a
            # smaller cycle switches on the noise guard, late, and grows until it runs away)
            raise IdentificationError(
                f"altitude: the altitude estimate is too noisy for the relay test: its noise "
                f"band is {100 * alt.band:.1f} cm ({cfg.noise_band_sigmas:g} sigma, measured on "
                f"the ground), so each relay half-cycle would need {100 * arm:.0f} cm to arm "
                f"its switch (beta {alt.beta:g}), over the "
                f"{100 * cfg.runaway_floor_alt_max_m / cfg.runaway_factor:.0f} cm its run-away "
                f"guard leaves room for; the relay is not started: "
                f"give the autopilot a less noisy height (a range finder, a filtered barometer) "
                f"or tune this vehicle by hand")

    def step(self, s: FlightState, z: float, new: bool) -> float:
        """Normalised thrust for this tick (``z``: height over take-off, m; ``new``: a new
        position sample)."""
        sh = self.sh
        t = sh.loops[Loop.ALTITUDE]
        if t.pd is not None:
            # where its relay oscillated (the climb may have come to rest under z_ref_m): a
            # step would disturb the x/y tests that start now
            u = t.pd.step(sh.takeoff.z_relay_m, z, s.vz_up_m_s)
        else:
            relay = sh.takeoff.relay
            before = float(relay.state[0]) if relay is not None else 0.0
            zf = sh.z_f - sh.origin[2]  # smoothed with the climb rate, as x and y
            sh.takeoff.no_brake = sh.config.brake_after_attitude and not sh.inner_done
            crept = sh.takeoff.creep_folded
            u = sh.takeoff.step(s.t_pos_s, zf, s.vz_up_m_s)
            if sh.takeoff.creep_folded and not crept:
                guess, hover = float(sh.takeoff.relay_bias or 0.0), sh.takeoff.creep_hover
                sh.events.append(
                    f"altitude: the climb crept at {s.vz_up_m_s:.2f} m/s, {zf:.2f} m up, on a "
                    f"hover guess {guess:.3f} ({100 * (guess / hover - 1):+.0f} %): hover "
                    f"thrust taken as {hover:.3f}, what held it")
            if sh.takeoff.switched:
                t.bias = sh.takeoff.u_z0
                if relay is not None:
                    ext, runaways = t.ext, t.runaways
                    sh.watch(t, relay, sh.takeoff.z_relay_m - zf, before)
                    self.half_unarmed(t, relay, ext, before, runaways)
                cycles = t.status.cycles
                sh.feed(t, s.t_pos_s, u, zf, new)
                if t.status.cycles > cycles and self.lopsided(t):
                    sh.takeoff.resettle(hover=float(np.mean(t.watch.last_cycles(2)[1])))
                    sh.events.append(
                        "altitude: two relay cycles in a row did not cross the set point (a "
                        "lopsided cycle); the relay starts again once the climb controller "
                        "holds the set point")
                    t.restart_detection()
        t.u = u
        return u

    def half_unarmed(self, t: LoopTest, relay: MRFT, ext: float, before: float,
                     runaways: int) -> None:
        """Raise h when every other switch comes before the threshold armed.

        A half-cycle too small to clear the noise band (``|e_ext| (1 + beta)``) switches on
        the relay's noise guard instead, late: the other half then swings out further each
        cycle until it runs away (a lead switch leaves the error on the far side, the small
        half never arms). Two unarmed switches in a row raise h already
        (:meth:`~mrft_gcs.flight.phases.shared.Shared.watch`); this catches them alternating.
        """
        st = float(relay.state[0])
        if t.runaways > runaways or t.state is not LoopState.RELAY:
            self._unarmed.clear()
            return
        if before == 0 or st == before or t.switches <= 2:
            return
        self._unarmed.append(abs(ext) * (1 + t.beta) <= t.band)
        if sum(self._unarmed) >= 2 and self.sh.raise_h(
                t, self.sh.config.h_raise, "half of each cycle too small for the measured "
                                           "noise: its switches came before the threshold armed"):
            self._unarmed.clear()

    def lopsided(self, t: LoopTest) -> bool:
        """The altitude relay's last two cycles both miss the set point in a half-cycle.

        Identification would refuse them (:func:`~mrft_gcs.features.cycle_features`); seen
        at once, the relay is started over from the set point instead of waiting for three
        steady cycles of a slow (0.9 s) lopsided mode first.
        """
        if t.state is not LoopState.RELAY or t.status.cycles < 2:
            return False
        _, u, y = t.watch.last_cycles(2)
        if u.size < 8:
            return False
        high = u > 0.5 * (u.max() + u.min())
        rises = np.concatenate([[0], rising_switches(u)])  # the window opens on a rise
        falls = np.flatnonzero(high[:-1] & ~high[1:]) + 1
        e = self.sh.takeoff.z_relay_m - y
        if len(rises) != 3:
            return False
        for a, b in zip(rises[:-1], rises[1:], strict=True):
            f = falls[(falls > a) & (falls < b)]
            if f.size != 1 or crosses_setpoint(e, a, f[0], b):
                return False
        return True
