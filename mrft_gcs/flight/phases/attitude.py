"""The roll and pitch relays (torque path), from lift-off to their identified PDs.

Each relay starts at lift-off at ``h_att_start`` and is sized on its first period (or at once
on a first swing that tilts too far): h so that the axis swings about ``att_amp_max_rad``,
the bias at the torque that holds the axis. Before that, from its second switch on, the relay
is centred on the torque bias measured from its first swings (:func:`torque_bias_fit`): a
CoM offset otherwise weakens every other push, and the swing that push must brake grows.
Where the same fit predicts a cycle over ``att_pred_amp_rad`` (:func:`predicted_swing`), the
push then starting brakes the swing under way harder and the relay takes a smaller h as the
axis turns: both relays run at once, and their first swings add up. Later periods resize a
relay whose swing grew too large or whose mean torque moved off its bias. A relay that
pushes the axis away before it is sized is turned round; a run-away is held by a damping PD
until the axis is back inside its cycle (:meth:`~mrft_gcs.flight.phases.shared.Shared.watch`).
A relay takes a new set point (the bounding relay's steps) only at a switch, and a smaller h
found on a period at the turn of the axis that ended it, without a restart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrft_gcs.flight.controllers import catch_pd
from mrft_gcs.flight.phases.liftoff import LiftoffDetector
from mrft_gcs.flight.phases.shared import Shared
from mrft_gcs.flight.phases.state import AUTOPILOT_ATTITUDE, LoopState, LoopTest
from mrft_gcs.identify import RelaySettings
from mrft_gcs.loops import Loop
from mrft_gcs.profiles import Actuation
from mrft_gcs.relay import MRFT

__all__ = ["AttitudeRelays", "TorqueFit", "predicted_swing", "torque_bias_fit"]

#: loop delays (s) and motor lags (s, first order) the torque-bias fit tries: a link round
#: trip and the telemetry, from a wired loopback to a slow radio; small to large motors
_FIT_DELAYS_S = tuple(0.01 * k for k in range(16))
_FIT_LAGS_S = (0.0, 0.02, 0.04, 0.06, 0.08)
#: fits within this factor of the best one's squared error count as fitting nearly as well
_FIT_NEAR = 2.0
#: relay switches after which the fit is no longer tried (the first period sizes the relay)
_CENTRE_SWITCHES = 8


@dataclass(frozen=True)
class TorqueFit:
    """An attitude axis as a double integrator behind a delay: ``y'' = K (u(t - d) + b)``.

    Attributes
    ----------
    gain : float
        K, angular acceleration per unit of normalised torque (rad/s^2).
    bias : float
        b, the torque the vehicle adds to the command (normalised; a CoM offset, a trim).
    bias_se : float
        Uncertainty of ``bias`` (normalised torque): its standard error from the residuals,
        or half its spread over the delays and lags that fit nearly as well, the larger.
    delay_s : float
        d, the loop delay that fits best (s).
    r2 : float
        Share of the rate's variance the fit explains.
    lag_s : float
        T, the motor lag (first order) that fits best (s).
    drag : float
        Rotational damping, ``y'' += -drag y'`` (1/s; 0 where no angle was fitted).
    """

    gain: float
    bias: float
    bias_se: float
    delay_s: float
    r2: float
    lag_s: float = 0.0
    drag: float = 0.0


def torque_bias_fit(t_cmd: np.ndarray, u_cmd: np.ndarray, t_s: np.ndarray, rate: np.ndarray,
                    angle: np.ndarray | None = None, delays_s: tuple[float, ...] = _FIT_DELAYS_S,
                    lags_s: tuple[float, ...] = _FIT_LAGS_S) -> TorqueFit | None:
    """Fit the axis' rate to the relay's torque: ``rate(t) = r0 + K int(m(s) + b) ds``, ``m``
    the command ``u(t - d)`` through a first-order lag ``T`` (the motors).

    Linear least squares in ``(r0, K, K b)`` for each delay ``d`` of ``delays_s`` and lag
    ``T`` of ``lags_s``, the best kept; the integral form needs no differentiated (noisy)
    rate. Each relay level must act for a quarter of the samples or more (a fit on one
    level alone cannot tell K from b). ``t_cmd``, ``u_cmd``:
    the commands (s, normalised torque; each held until the next); ``t_s``, ``rate``: the
    rate samples fitted (s, rad/s), within the commands' span. None with fewer than 8
    samples, a command that does not change over them, or no positive K.

    Examples
    --------
    >>> t = np.arange(-0.1, 0.4, 0.004)
    >>> u = np.where(t < 0.0, -0.06, np.where(t < 0.2, 0.06, -0.06))
    >>> ud = np.interp(t - 0.03, t, u)  # acting 30 ms later
    >>> rate = np.concatenate([[0.0], np.cumsum(500.0 * (ud[:-1] + 0.02) * 0.004)])
    >>> f = torque_bias_fit(t, u, t[25:], rate[25:])
    >>> round(f.gain, -1), round(f.bias, 2), round(f.delay_s, 2), f.bias_se < 1e-3
    (500.0, 0.02, 0.03, True)
    """
    t_cmd, u_cmd, t_s, rate = (np.asarray(a, float) for a in (t_cmd, u_cmd, t_s, rate))
    if t_s.size < 8:
        return None
    dt = np.diff(t_s)
    # the command acting at each sample under each delay: the last one given d earlier
    k = np.searchsorted(t_cmd, t_s[None, :] - np.asarray(delays_s)[:, None] + 1e-9,
                        side="right") - 1
    ud = u_cmd[np.clip(k, 0, None)]
    hi = ud > 0.5 * (ud.max(axis=1) + ud.min(axis=1))[:, None]
    ok = (np.ptp(ud, axis=1) > 0) & (np.minimum(hi.mean(axis=1), 1 - hi.mean(axis=1)) >= 0.25)
    if not ok.any():
        return None
    ud, dl = ud[ok], np.asarray(delays_s)[ok]
    # through each motor lag (first order; 0: none), all delays and lags at once
    lags = np.asarray(lags_s, float)
    alpha = np.where(lags[:, None] > 0, -np.expm1(-dt[None, :] / np.maximum(lags, 1e-9)[:, None]),
                     1.0)
    m = np.empty((lags.size, *ud.shape))
    m[..., 0] = ud[None, :, 0]
    for i in range(1, t_s.size):
        prev = m[..., i - 1]
        m[..., i] = np.where(lags[:, None] > 0,
                             prev + alpha[:, i - 1, None] * (ud[None, :, i - 1] - prev),
                             ud[None, :, i])
    U = np.concatenate([np.zeros((*m.shape[:2], 1)), np.cumsum(m[..., :-1] * dt, axis=-1)],
                       axis=-1).reshape(-1, t_s.size)
    fixed = [np.ones_like(t_s), t_s - t_s[0]]
    if angle is not None:  # rotational drag: its integral is the angle swept
        fixed.append(np.asarray(angle, float) - float(angle[0]))
    # columns (r0, K, K b[, drag]) of every candidate, least squares through the normal
    # equations on unit-scaled columns
    a = np.stack([np.broadcast_to(fixed[0], U.shape), U,
                  *(np.broadcast_to(c, U.shape) for c in fixed[1:])], axis=-1)
    scale = np.sqrt(np.einsum("cni,cni->ci", a, a)) + 1e-300
    an = a / scale[:, None, :]
    x = np.linalg.solve(np.einsum("cni,cnj->cij", an, an) + 1e-12 * np.eye(a.shape[-1]),
                        np.einsum("cni,n->ci", an, rate)[..., None])[..., 0] / scale
    res = rate[None, :] - np.einsum("cni,ci->cn", a, x)
    sse_all = np.einsum("cn,cn->c", res, res)
    b_all = np.where(x[:, 1] > 0, x[:, 2] / np.where(x[:, 1] > 0, x[:, 1], 1.0), np.inf)
    c = int(np.argmin(sse_all))
    sse, x, a = float(sse_all[c]), x[c], a[c]
    d = float(dl[c % dl.size])
    # the delays and lags that fit nearly as well bound the bias too: a short record can
    # trade the bias against the delay (a model error the residuals do not show)
    near = b_all[sse_all <= _FIT_NEAR * sse]
    spread = 0.5 * float(near.max() - near.min()) if np.isfinite(near).all() else math.inf
    var = float(np.sum((rate - rate.mean()) ** 2))
    if not x[1] > 0 or var <= 0:
        return None
    # the bias' standard error by the delta method on b = (K b) / K
    cov = sse / max(t_s.size - x.size, 1) * np.linalg.pinv(a.T @ a)
    g = np.zeros(x.size)
    g[1], g[2] = -x[2] / x[1] ** 2, 1.0 / x[1]
    se = max(math.sqrt(max(float(g @ cov @ g), 0.0)), spread)
    drag = max(-float(x[3]), 0.0) if x.size > 3 else 0.0
    return TorqueFit(float(x[1]), float(x[2] / x[1]), se, d, 1.0 - sse / var,
                     float(lags[c // dl.size]), drag)


def predicted_swing(fit: TorqueFit, h: float, beta: float) -> tuple[float, float]:
    """Period (s) and swing (rad) of the MRFT cycle a relay of amplitude ``h`` (normalised
    torque) and parameter ``beta`` drives on the fitted axis (describing function).

    The axis ``K e^(-s d) / (s (s + c) (T s + 1))`` oscillates where its phase lag past
    -180 deg equals the MRFT's lead ``arcsin(-beta)``, at a swing ``4 h |W| / pi``.
    (nan, nan) where there is no such frequency (no lead and no delay or lag).

    Examples
    --------
    >>> f = TorqueFit(500.0, 0.0, 0.0, 0.03, 1.0)
    >>> period, amp = predicted_swing(f, 0.06, -0.7)
    >>> round(period, 3), round(amp, 3)
    (0.243, 0.057)
    """
    phi = math.asin(-beta) + 0.5 * math.pi
    a, d, lag = fit.drag, fit.delay_s, fit.lag_s

    def lag_phase(w: float) -> float:
        return (math.atan2(w, a) if a > 0 else 0.5 * math.pi) + w * d + math.atan(w * lag)

    lo, hi = 1e-3, 1e4
    if not lag_phase(lo) < phi < lag_phase(hi):
        return math.nan, math.nan
    for _ in range(100):  # bisection: the phase rises with the frequency
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if lag_phase(mid) < phi else (lo, mid)
    w = math.sqrt(lo * hi)
    mag = fit.gain / (w * math.hypot(w, a) * math.hypot(1.0, w * lag))
    return 2.0 * math.pi / w, 4.0 * h * mag / math.pi


def _swing_peak(fit: TorqueFit, hist: np.ndarray, t_s: float, y: float, rate: float,
                u: float, horizon_s: float = 1.0, dt: float = 2e-3) -> tuple[float, float]:
    """Angle (rad, as ``y``) and time (s) where the fitted axis next turns: from ``y``,
    ``rate`` at ``t_s`` under the commands ``hist`` (t, u) so far, then ``u`` held."""
    m = None
    for i in range(int(horizon_s / dt)):
        tc = t_s + i * dt - fit.delay_s
        k = int(np.searchsorted(hist[:, 0], tc, side="right")) - 1
        ud = u if tc >= t_s else float(hist[max(k, 0), 1])
        m = ud if m is None or fit.lag_s <= 0 else m + (ud - m) * min(dt / fit.lag_s, 1.0)
        w = rate + (fit.gain * (m + fit.bias) - fit.drag * rate) * dt
        if w * rate < 0:
            return y, t_s + i * dt
        y, rate = y + rate * dt, w
    return y, t_s + horizon_s


class AttitudeRelays:
    """Roll and pitch: relay, sizing, run-away catch, then the identified PD.

    Parameters
    ----------
    shared : Shared
        The sequence's shared state.
    settings : RelaySettings
        MRFT beta and the h to size towards (normalised torque).
    liftoff : LiftoffDetector
        Its rate thresholds tell a turn of the axis from gyro noise.
    """

    def __init__(self, shared: Shared, settings: RelaySettings,
                 liftoff: LiftoffDetector) -> None:
        self.sh = shared
        self.liftoff = liftoff
        #: the set point each relay's error is taken from (rad): the set point given, as it
        #: was at the relay's last switch (:meth:`step`)
        self._ref = {Loop.ROLL: math.nan, Loop.PITCH: math.nan}
        cfg = shared.config
        for lp in (Loop.ROLL, Loop.PITCH):
            t = shared.loops[lp]
            t.beta = settings.beta
            t.h_goal = max(settings.h, cfg.h_att_min)
            t.h, t.sized = min(t.h_goal, cfg.h_att_start), False
            if cfg.actuation is Actuation.ATTITUDE:
                t.state = LoopState.LEFT_ALONE
                t.note = AUTOPILOT_ATTITUDE

    def step(self, loop: Loop, ref: float, y: float, rate: float, t_s: float, new: bool,
             airborne: bool) -> float:
        """Normalised torque of ``loop`` for this tick.

        Parameters
        ----------
        ref, y : float
            Angle set point and measured angle (rad).
        rate : float
            Measured body rate (rad/s).
        t_s : float
            Time of the attitude sample (s); ``new``: it is a new sample.
        airborne : bool
            Lift-off seen: the relay may start.
        """
        t = self.sh.loops[loop]
        if t.pd is not None:
            u = t.pd.step(ref, y, rate)
        elif not airborne:
            u = 0.0
        else:
            if t.state is LoopState.WAITING:
                t.band = self.sh.noise_band(loop)
                t.relay = MRFT(t.beta, t.h, band=t.band)
                t.state, t.t_relay_start_s = LoopState.RELAY, t_s
            assert t.relay is not None
            if t.catch is not None:
                # back to the relay once inside its own cycle's envelope (angle and rate)
                period, amp = t.cycle
                if t_s - t.t_catch_s < 3 * period:  # a resized relay: at rest first
                    amp *= t.catch_release
                e = ref - y
                self._ref[loop] = ref  # the catch brings the axis to the set point
                if abs(e) < amp and abs(rate) < 2 * math.pi * amp / period:
                    t.from_rest = t.catch_release < 1.0
                    t.catch, t.catch_release = None, 1.0
                    t.catch_flips, t.catch_sign = 0, 0.0
                    t.t_rest_s = math.nan
                else:
                    kc, kd = t.catch
                    lim = self.sh.config.catch_torque_factor * t.h
                    raw = kc * e - kd * rate
                    if abs(raw) >= lim:
                        self._count_chatter(t, math.copysign(1.0, raw))
                    # about the relay's bias: the torque that holds the axis (a CoM offset)
                    u = t.bias + min(lim, max(-lim, raw))
                    self._rest_bias(t, t_s, u, rate)
                    t.u = u
                    return u
            r = t.relay
            at_switch = self.sh.config.att_ref_at_switch
            before = float(r.state[0])
            if before == 0 or not math.isfinite(self._ref[loop]) or not at_switch:
                self._ref[loop] = ref  # a relay (re)starting takes the set point as it is
            e = self._ref[loop] - y
            u = float(r.step(e)[0])
            now = float(r.state[0])
            if before != 0 and now != before and (ref - self._ref[loop]) * now > 0:
                # the bounding relay steps the set point (0.05 rad): taken mid-swing, the
                # step moved the error past the MRFT's threshold, switching it early into a
                # short cycle whose small amplitude then had a normal swing caught as a
                # run-away. It is taken at a switch into the half-cycle whose error swing
                # it enlarges: into the other, an off-centre swing could stop short of the
                # new set point, leaving the relay unarmed and pushing the axis on
                self._ref[loop] = ref
                e = ref - y
                r.ext[:] = max(e, 0.0) if now > 0 else min(e, 0.0)
                r.entry[:] = e
            self.sh.watch(t, r, e, before, -rate)
            if t.relay is not None and self._drives_away(t, e, -rate):
                # the MRFT's lead braked a return swing short of its set point (too little
                # swing to arm the switch: a torque bias, an agile vehicle at its first h)
                # and now pushes the axis away from it, which tilts a light vehicle far
                # over. The relay is turned round at once, this point its new extreme
                r.state[:] = 1.0 if e >= 0 else -1.0
                r.ext[:] = r.entry[:] = e
                r.first[:] = False
                r.switches += 1
                u = float(r.bias[0] + r.h[0] * r.state[0])
                t.pushed_away += 1
            if t.relay is not None and not t.sized and not t.centred:
                u = self._centre(t, t_s, u, y, rate, new)
            if math.isfinite(t.h_planned) and self._take_planned_h(t, t_s):
                assert t.relay is not None
                u = float(t.relay.bias[0] + t.relay.h[0] * t.relay.state[0])
            self.sh.feed(t, t_s, u, y, new)
            if new and t.relay is not None:
                self._size(t, t_s, u, y, e, -rate)
            st = t.status
            if (st.cycles >= 2 and st.spread < 0.15 and math.isfinite(st.period_s)
                    and st.amplitude > 0):
                t.cycle = (st.period_s, st.amplitude)
        t.u = u
        return u

    def _rest_bias(self, t: LoopTest, t_s: float, u: float, rate: float) -> None:
        """A catch that holds the axis at rest outside its hand-back envelope holds it on the
        torque bias it lacks (its PD has no I): after a cycle's period at rest, that torque
        is the relay's bias, or the catch never hands back and the vehicle drifts on its
        lean (a 7 deg lean for 10 s went 5 m)."""
        period, amp = t.cycle  # the whole cycle (not the envelope narrowed after a resize)
        if not (abs(rate) < 0.1 * 2 * math.pi * amp / period):
            t.t_rest_s = math.nan
            return
        if math.isnan(t.t_rest_s):
            t.t_rest_s = t_s
            return
        if (t_s - t.t_rest_s < period or abs(u) > self.sh.config.att_bias_max
                or abs(u - t.bias) < 1e-9):
            return
        self.sh.events.append(f"{t.loop.value}: held at rest off its set point by the catch: "
                              f"bias {t.bias:+.3g} -> {u:+.3g} (the torque that holds it)")
        t.bias = u
        if t.relay is not None:
            t.relay.bias[:] = u
        t.t_rest_s = math.nan

    def _centre(self, t: LoopTest, t_s: float, u: float, y: float, rate: float,
                new: bool) -> float:
        """Before the relay is sized: at each switch, centre it on the torque bias fitted to
        its swings so far (:func:`torque_bias_fit`); returns this tick's output.

        Commands are recorded from the relay's start, rates once the vehicle is
        ``att_centre_z_m`` off the ground (the ground carries torque until then). A fit is
        taken where it explains ``att_centre_r2`` of the rate and pins the bias within
        ``att_centre_se`` of h; the relay then takes it as its bias where it is over
        ``att_bias_min`` of h off the relay's, under h and within ``att_bias_max``. The
        relay is not restarted: the new bias acts from this switch on, on the push that
        brakes the swing now starting.
        """
        cfg, r, sh = self.sh.config, t.relay, self.sh
        assert r is not None
        if not cfg.att_centre_r2:
            return u
        cmd = t.centre_cmd
        if not cmd or cmd[-1][1] != u:
            cmd.append((t_s, u))
        if new and sh.z_f - sh.origin[2] > cfg.att_centre_z_m:
            t.centre_rate.append((t_s, rate, y))
        n = int(r.switches[0])
        if n == t.centre_switches:
            return u
        t.centre_switches = n
        if n > _CENTRE_SWITCHES:  # (a relay restarted again and again): its periods size it
            t.centred = True
            return u
        if len(t.centre_rate) < 8:
            return u
        tc, uc = np.array(cmd).T
        tr, wr, yr = np.array(t.centre_rate).T
        fit = torque_bias_fit(tc, uc, tr, wr, yr)
        if (fit is None or fit.r2 < cfg.att_centre_r2 or fit.bias_se > cfg.att_centre_se * t.h
                or fit.delay_s >= _FIT_DELAYS_S[-1] or not abs(fit.bias) < t.h):
            return u  # not yet pinned down: the next switch tries again
        t.centred = True
        t.centre_cmd, t.centre_rate = [], []
        bias = -fit.bias
        if not (cfg.att_bias_min * t.h < abs(bias - t.bias) and abs(fit.bias) < t.h
                and abs(bias) <= cfg.att_bias_max):
            return self._plan_h(t, fit, cmd, t_s, y, rate, u)
        self.sh.events.append(
            f"{t.loop.value}: relay centred on the torque bias of its first swings: bias "
            f"{t.bias:+.3g} -> {bias:+.3g} (fit: {fit.gain:.3g} rad/s^2 per unit torque, "
            f"{1e3 * fit.delay_s:.0f} ms, R^2 {fit.r2:.2f})")
        t.bias = bias
        r.bias[:] = bias
        u = float(bias + r.h[0] * r.state[0])
        cmd.append((t_s, u))
        return self._plan_h(t, fit, cmd, t_s, y, rate, u)

    def _plan_h(self, t: LoopTest, fit: TorqueFit, cmd: list, t_s: float, y: float,
                rate: float, u: float) -> float:
        """Before the first period: where the fit predicts a cycle swinging the axis over
        ``att_pred_amp_rad`` at the starting h, plan the h that swings it that far (no
        smaller than the noise band needs, nor ``h_att_floor``), taken as the axis next turns
        (:meth:`_take_planned_h`). The push now starting brakes the swing under way: it is
        raised (up to ``h_goal``) where the fitted model run forward (:func:`_swing_peak`)
        carries that swing past 0.85 of that far from level (the set point of the take-off
        relays). Returns this tick's output."""
        cfg, r = self.sh.config, t.relay
        assert r is not None
        period, amp = predicted_swing(fit, t.h, t.beta)
        if not (cfg.att_pred_amp_rad and amp > cfg.att_pred_amp_rad):
            return u
        per_h = amp / t.h
        sigma = t.band / cfg.noise_band_sigmas if math.isfinite(t.band) else 0.0
        h_noise = sigma / (0.7 * cfg.max_noise_ratio * per_h)
        h = max(cfg.att_pred_amp_rad / per_h, min(h_noise, t.h), cfg.h_att_floor)
        if not h < 0.95 * t.h:
            return u
        t.h_planned = h
        st, bias = float(r.state[0]), float(r.bias[0])
        hist = np.array(cmd[:-1]) if len(cmd) > 1 else np.array([(t_s, u)])

        def peak(hb: float) -> float:
            return _swing_peak(fit, hist, t_s, y, rate, bias + st * hb)[0]

        lim = 0.85 * cfg.att_pred_amp_rad
        hb = t.h
        if abs(peak(hb)) > lim and abs(peak(t.h_goal)) < abs(peak(hb)):
            lo, hi = t.h, t.h_goal
            for _ in range(12):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if abs(peak(mid)) > lim else (lo, mid)
            hb = hi
            r.h[:] = hb
        # the smaller h reaches the axis a delay and a lag after it is sent
        t.t_h_planned_s = (_swing_peak(fit, hist, t_s, y, rate, bias + st * hb)[1]
                           - fit.delay_s - fit.lag_s)
        self.sh.events.append(
            f"{t.loop.value}: the fit predicts a {amp:.3g} rad swing (period {period:.2f} s) "
            f"at h {t.h:.3g}: h {h:.3g} from the next turn of the axis"
            + (f", the swing under way braked at h {hb:.3g}" if hb != t.h else ""))
        return float(bias + r.h[0] * st)

    def _take_planned_h(self, t: LoopTest, t_s: float) -> bool:
        """Take the planned h (:meth:`_plan_h`) a delay and a lag before the fit predicts the
        axis turns: taken at a switch, a smaller push would brake the swing then starting
        less and let it swing further; acting from the turn on, it only accelerates the
        axis back less. True where taken (this tick's output changes)."""
        r = t.relay
        if r is None or t.sized:
            t.h_planned = math.nan  # sized on a period or a swing first: that h holds
            return False
        if t_s < t.t_h_planned_s:
            return False
        h, t.h_planned = t.h_planned, math.nan
        t.h = h
        r.h[:] = h
        # the first period is measured at the new h alone
        t.probe, t.turns, t.turn_sign = [], [], 0.0
        t.probe_rate.clear()
        return True

    def _count_chatter(self, t: LoopTest, side: float) -> None:
        """The catch's output sits at its limit on ``side``: count swings from one limit to
        the other and halve a catch that chatters (``catch_chatter_flips``)."""
        if t.catch_sign and side != t.catch_sign:
            t.catch_flips += 1
        t.catch_sign = side
        if t.catch is not None and t.catch_flips >= self.sh.config.catch_chatter_flips:
            kc, kd = t.catch
            t.catch = (0.5 * kc, 0.5 * kd)
            t.catch_flips, t.catch_sign = 0, 0.0
            self.sh.events.append(f"{t.loop.value}: the catch chattered at its limits "
                                  f"(sized on too small a cycle): its gains halved")

    def _drives_away(self, t: LoopTest, e: float, e_rate: float) -> bool:
        """Roll/pitch in its first cycles (until sized and two detector cycles): the relay
        pushes the axis away from its set point while it moves away, beyond twice the noise
        band. In a proper MRFT cycle the relay pushes away only to brake a swing that still
        moves towards the set point."""
        if t.sized and t.status.cycles >= 2 or t.catch is not None or t.relay is None:
            return False
        st = float(t.relay.state[0])
        band = t.band if math.isfinite(t.band) else 0.0
        return (st * e < 0 and e * e_rate > 0 and abs(e) > 2 * band
                and abs(e_rate) > self.liftoff.turn_rate(t.loop))

    # ------------------------------------------------------------------ sizing
    def _size(self, t: LoopTest, t_s: float, u: float, y: float, e: float,
              e_rate: float) -> None:
        """Roll/pitch relay sizing, on each new attitude sample while the relay runs.

        The first period (``h_att_start``) sets h and the bias; later periods resize a relay
        whose swing passes 1.25 x ``att_amp_max_rad`` (a first period from rest can fall
        short of the steady cycle) or whose mean torque moved off its bias by
        ``att_bias_min`` of h. A period runs from one turn of the axis (rate through zero)
        to the next turn the same way: the rate is zero at both ends, so the mean relay
        output over it is the torque that holds the axis (the plant integrates); from
        switch to switch it is not while the cycle still grows. Before the first period, a
        relay that cannot turn the axis back (a torque bias over h: pushed back, yet
        speeding away beyond ``att_amp_max_rad``) is doubled at once.
        """
        cfg, relay = self.sh.config, t.relay
        assert relay is not None
        st = float(relay.state[0])
        if not t.sized:
            t.probe_rate.append((t_s, st, e_rate))
            # pushed back for long enough to have acted, yet still speeding outward (a normal
            # swing slows down once the push-back acts)
            back = [r for r in t.probe_rate if r[0] >= t_s - cfg.att_bias_window_s]
            if (len(back) >= 3 and back[0][0] <= t_s - 0.9 * cfg.att_bias_window_s
                    and all(r[1] == st for r in back)
                    and abs(e) > cfg.att_amp_max_rad and st * e > 0 and e * e_rate > 0
                    and abs(e_rate) > abs(back[0][2]) and t.h < t.h_goal):
                h = min(t.h_goal, 2.0 * t.h)
                self.sh.events.append(
                    f"{t.loop.value}: relay amplitude raised from {t.h:.3g} to "
                    f"{h:.3g} (it could not turn the axis back: a torque bias)")
                t.h = h
                relay.h[:] = h
                t.probe, t.turns, t.turn_sign = [], [], 0.0
                t.probe_rate.clear()
                return
        n = int(relay.switches[0])
        if n < t.probe_switches:  # the relay was restarted (a run-away): periods from here
            t.probe, t.turns, t.turn_sign = [], [], 0.0
        t.probe_switches = n
        if n == 0:
            return  # from the relay's first switch on
        rate = -e_rate
        t.probe.append((t_s, u, y, rate))
        thr = self.liftoff.turn_rate(t.loop)
        if t.turn_sign == 0.0:
            t.turn_sign = math.copysign(1.0, rate) if abs(rate) > thr else 0.0
        elif rate * t.turn_sign < -thr:  # a turn, with hysteresis against gyro noise
            t.turn_sign = -t.turn_sign
            t.turns.append(len(t.probe) - 1)
            if len(t.turns) >= 3:
                self._period_done(t)
            elif not t.sized and len(t.turns) == 2:
                self._first_swing(t)

    def _first_swing(self, t: LoopTest) -> None:
        """Size at once on the first swing from turn to turn if it passed twice
        ``att_amp_max_rad``: a full first period of a light, agile vehicle at
        ``h_att_start`` would tilt it far over (its bias is measured on later periods)."""
        i, j = t.turns
        seg = np.array(t.probe[i:j + 1])
        amp = 0.5 * float(np.ptp(seg[:, 2]))
        if amp > 2.0 * self.sh.config.att_amp_max_rad:
            t.sized = True
            t.probe_rate.clear()
            t0, t1 = float(seg[0, 0]), float(seg[-1, 0])
            self._resize(t, np.array([t0, t0 + 2.0 * (t1 - t0)]), amp, t.bias,
                         "its first swing")

    def _period_done(self, t: LoopTest) -> None:
        """A period from turn to turn is complete: size the relay on it if due."""
        cfg = self.sh.config
        i, j = t.turns[-3], t.turns[-1]
        rec = np.array(t.probe[i:j + 1])
        # keep what the next period needs: from the turn before the last on
        k = t.turns[-2]
        t.probe = t.probe[k:]
        t.turns = [0, j - k]
        if rec.shape[0] < 4:
            return
        ts, us, ys = rec[:, 0], rec[:, 1], rec[:, 2]
        dt = np.diff(ts)
        mean_u = float(np.sum(us[:-1] * dt) / np.sum(dt))
        amp = 0.5 * float(np.ptp(ys))
        if not t.sized:
            t.sized = True
            t.probe_rate.clear()
            self._resize(t, ts, amp, mean_u, "its first period")
            return
        if t.resizes >= cfg.att_max_resizes or not amp > 0:
            return
        if abs(ys[-1] - ys[0]) > 0.25 * amp:
            t.bias_votes.clear()
            return  # not yet periodic (growing or shrinking): its mean torque is no bias
        t.bias_votes.append(mean_u)
        # a new bias only on two periods in a row that agree (a ground-station stall holds
        # the torque the vehicle gets, not the one recorded: one period can be far off)
        tol = cfg.att_bias_min * t.h
        m = t.bias_votes[-2:]
        off = (len(m) == 2 and abs(m[0] - m[1]) < tol
               and all(abs(x - t.bias) > tol for x in m))
        if amp > 1.25 * cfg.att_amp_max_rad or off:
            self._resize(t, ts, amp, float(np.mean(m)) if off else t.bias, "a period")

    def _resize(self, t: LoopTest, ts: np.ndarray, amp: float, mean_u: float,
                what: str) -> None:
        """Set roll/pitch's h and bias from one period (its times, swing ``amp`` in rad, mean
        torque): h no larger than swings the axis ``att_amp_max_rad`` (the swing is
        proportional to h), the bias at the mean torque; the relay restarts at rest."""
        cfg, relay = self.sh.config, t.relay
        assert relay is not None
        h0 = t.h
        h = t.h_goal if what.startswith("its first") else h0
        if amp > 0:
            t.amp_per_h = amp / h0
            if t.amp_per_h * h > 1.25 * cfg.att_amp_max_rad:
                # (with a margin: the first period after lift-off is no steady cycle yet and
                # can swing twice as far as the steady one)
                h = cfg.att_amp_max_rad / t.amp_per_h
            # no smaller than the noise needs (the amplitude ``ready`` raises to), within reason
            sigma = t.band / cfg.noise_band_sigmas if math.isfinite(t.band) else 0.0
            h_noise = sigma / (0.7 * cfg.max_noise_ratio * t.amp_per_h)
            h = max(h, min(h_noise, t.h_goal, 1.5 * cfg.att_amp_max_rad / t.amp_per_h))
        h = max(h, cfg.h_att_floor)
        bias = mean_u if (cfg.att_bias_min * min(h, h0) < abs(mean_u - t.bias)
                          and abs(mean_u) <= cfg.att_bias_max) else t.bias
        notes = []
        if abs(h - h0) > 0.01 * h0:
            notes.append(f"amplitude {h0:.3g} -> {h:.3g}")
        if bias != t.bias:
            notes.append(f"bias {t.bias:+.3g} -> {bias:+.3g} (the mean torque)")
        if not notes:
            return
        # a smaller h alone is taken at once: sizing runs at a turn of the axis, where it only
        # accelerates the return swing less (as a planned h, :meth:`_take_planned_h`)
        at_turn = cfg.att_resize_at_turn and amp > 0 and h < h0 and bias == t.bias
        self.sh.events.append(f"{t.loop.value}: relay sized on {what} ({amp:.3g} rad at h "
                              f"{h0:.3g}): " + ", ".join(notes)
                              + (", from this turn of the axis" if at_turn else ""))
        t.resizes += 1
        t.h, t.bias = h, bias
        relay.h[:] = h
        relay.bias[:] = bias
        t.probe, t.turns, t.turn_sign = [], [], 0.0
        t.bias_votes.clear()
        t.unarmed = t.switches = 0
        t.ext = 0.0
        t.restart_detection()
        if amp > 0:  # the cycle to expect at the new h (sizes the run-away catch)
            t.cycle = (float(ts[-1] - ts[0]), t.amp_per_h * h)
        if amp > 0 and not at_turn:
            relay.reset()
            # the relay restarts from rest at its set point: an MRFT (beta -0.7) switched to a
            # smaller h or a new bias mid-swing swung out further or locked into a lopsided
            # cycle that never crossed its set point, a sign relay restarted off its set point
            # swung out to twice the cycle, and a larger h taken mid-swing under stalls
            # tilted the vehicle twice as far as with the restart. A damping PD sized on that
            # cycle brings the axis there first
            t.catch = catch_pd(h, *t.cycle)
            t.catch_release = cfg.att_restart_envelope
            t.t_catch_s = float(ts[-1])
