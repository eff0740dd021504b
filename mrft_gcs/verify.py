"""Trajectory check after tuning (docs/verify.md): fly a minimum-snap figure-eight on the gains.

How it flies (stated in every result, :attr:`VerifyResult.method`):

* The gains are read from the vehicle (:class:`~mrft_gcs.params.ParamClient`) and turned back
  into PD gains with the autopilot profile (:func:`~mrft_gcs.profiles.params_to_gains`).
* Position and altitude are closed **on the ground station**, with exactly those PD gains,
  ``u = Kc e + Kd (v_ref - v)`` per axis (x and y: tilt in rad; altitude: normalised thrust
  deviation), plus feed-forward of the reference. The outputs become one desired acceleration
  (tilt ``u`` gives ``g u``; thrust deviation ``u`` gives ``g u / hover``), and the desired force
  ``m (a - g)`` becomes attitude and thrust as in the paper's eq. 3-7: body z along the force,
  heading held, thrust ``hover |f| / g``. These go to the vehicle as SET_ATTITUDE_TARGET in
  OFFBOARD at 250 Hz, and the **onboard attitude loop flies them on its own MC_* gains** (the
  tuned roll/pitch PD).
* Feed-forward: the reference acceleration always. Given the loops' models (the tune report's
  ``loops.*.model``, or a SITL's true linear models), the attitude feed-forward is the inverse of
  the side model ``K e^{-tau s} / (s (T2 s + 1))`` behind the closed attitude loop:
  ``u_ff = (T2 a + v) / K`` taken ``tau + T_att`` seconds ahead, ``T_att`` being the phase lag
  of the closed attitude loop at the lap frequency (and alike for altitude with ``T1``). That
  cancels drag and delay, which the PD alone would leave as lag error.

The vehicle takes off (or, if already flying, starts from where it is) straight up to the
figure's start point, its centre crossing, settles, then runs the path from rest
(:func:`~mrft_gcs.trajectory.ramp_in`), flies ``settle_laps`` laps unmeasured, ``laps`` laps
measured, slows to rest and lands (or holds in the position mode). The error is that of the
position the vehicle reports (LOCAL_POSITION_NED, requested at 250 Hz) against the reference at
the report's own timestamp, over whole laps only.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mrft_gcs.errors import (
    InputFileError,
    LinkError,
    MissingDependency,
    SafetyAbort,
    UsageError,
)
from mrft_gcs.link import SetpointStreamer, VehicleLink
from mrft_gcs.link.modes import mode_matches
from mrft_gcs.loops import Loop
from mrft_gcs.params import ParamClient
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import closed_inner_response, inner_response, side_response
from mrft_gcs.profiles import G_M_S2, AutopilotProfile, PDGains, gains_to_params, load_profile
from mrft_gcs.profiles import params_to_gains as _params_to_gains
from mrft_gcs.sitl import load_airframe
from mrft_gcs.telemetry import Attitude, AttitudeTarget, AutopilotFamily, Heartbeat, LocalPosition
from mrft_gcs.trajectory import PiecewisePoly, TrajectorySample, evaluate, figure_eight

__all__ = [
    "FlightPlan",
    "TrackingErrors",
    "VerifyResult",
    "plan_figure8",
    "flight_reference",
    "tracking_errors",
    "desired_acceleration",
    "attitude_from_acceleration",
    "feedforward_leads",
    "reference_gains",
    "reference_params",
    "verify_figure8",
    "plot_verify",
    "load_models",
]

_SMOOTH = {4: 35.0, 5: -84.0, 6: 70.0, 7: -20.0}  # s(u): 0 -> 1, zero derivatives 1..3 at ends


def _smoothstep(u: np.ndarray, k: int) -> np.ndarray:
    """k-th derivative of the integral S(u) of s(u) (k = 0: S; S(1) = 1/2)."""
    out = np.zeros_like(u)
    for p, a in _SMOOTH.items():
        q = p + 1  # power in S
        if k <= q:
            out += a / q * math.perm(q, k) * u ** (q - k)
    return out


def _step(u: np.ndarray, k: int) -> np.ndarray:
    """k-th derivative of s(u) itself (a smooth 0 -> 1 step, C^3)."""
    out = np.zeros_like(u)
    for p, a in _SMOOTH.items():
        if k <= p:
            out += a * math.perm(p, k) * u ** (p - k)
    return out


# ------------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class FlightPlan:
    """Times (s, vehicle clock, relative to the start of control) and places (m, NED)."""

    path: PiecewisePoly
    start_ned_m: tuple[float, float, float]  # where control starts (ground or hover)
    centre_ned_m: tuple[float, float, float]  # the figure's centre and start point
    climb_s: float
    settle_s: float
    lead_s: float  # ramp-in and ramp-out time of the path
    settle_laps: int
    laps: int
    hold_s: float

    @property
    def figure_start_s(self) -> float:
        return self.climb_s + self.settle_s

    @property
    def window_s(self) -> tuple[float, float]:
        """The measured whole laps."""
        t0 = self.figure_start_s + self.lead_s + self.settle_laps * self.path.period_s
        return t0, t0 + self.laps * self.path.period_s

    @property
    def duration_s(self) -> float:
        return self.window_s[1] + self.lead_s + self.hold_s


def plan_figure8(start_ned_m: tuple[float, float, float], *, airborne: bool,
                 size_m: tuple[float, float] = (2.0, 1.0), period_s: float = 5.5, laps: int = 2,
                 settle_laps: int = 1, altitude_m: float = 1.0, climb_s: float = 3.0,
                 settle_s: float = 2.0, hold_s: float = 1.0) -> FlightPlan:
    """The flight: climb ``altitude_m`` from ``start_ned_m`` (none if ``airborne``), then laps.

    The figure's long side (``size_m[0]``) runs north, the short one east.
    """
    if laps < 1 or settle_laps < 0:
        raise UsageError(f"laps must be >= 1 and settle laps >= 0, got {laps}, {settle_laps}")
    if not airborne and not 0.3 <= altitude_m <= 20:
        raise UsageError(f"take-off altitude {altitude_m} m: use 0.3 to 20 m")
    path = figure_eight(size_m, period_s)
    n, e, d = (float(v) for v in start_ned_m)
    centre = (n, e, d if airborne else d - altitude_m)
    return FlightPlan(path, (n, e, d), centre, climb_s if not airborne else 0.5, settle_s,
                      period_s / 2, settle_laps, laps, hold_s)


def flight_reference(plan: FlightPlan, t_s: np.ndarray) -> TrajectorySample:
    """Reference position, velocity, acceleration, jerk (NED, arrays ``(n, 3)``) at ``t_s``.

    Snap is left at zero outside the path (it is not flown).
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    n = len(t)
    pos = np.tile(np.asarray(plan.centre_ned_m), (n, 1))
    vel, acc, jerk = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    # climb: smooth step of the altitude (C^3)
    dz = plan.centre_ned_m[2] - plan.start_ned_m[2]
    u = np.clip(t / plan.climb_s, 0.0, 1.0)
    climbing = (t > 0) & (t < plan.climb_s)
    pos[:, 2] = plan.start_ned_m[2] + dz * _step(u, 0)
    for k, arr in ((1, vel), (2, acc), (3, jerk)):
        arr[:, 2] = np.where(climbing, dz * _step(u, k) / plan.climb_s**k, 0.0)
    # path parameter: ramp in (rate 0 -> 1), full speed, ramp out (rate 1 -> 0), rest
    L, tf = plan.lead_s, plan.figure_start_s
    tr = t - tf
    t_out = plan.window_s[1] - tf
    ui = np.clip(tr / L, 0.0, 1.0)
    uo = np.clip((tr - t_out) / L, 0.0, 1.0)
    sigma = np.where(tr < L, L * _smoothstep(ui, 0),
                     np.where(tr < t_out, tr - L / 2,
                              t_out - L / 2 + L * (0.5 - _smoothstep(1 - uo, 0))))
    ramp_in, ramp_out = (tr > 0) & (tr < L), (tr > t_out) & (tr < t_out + L)
    rate = np.where(tr <= 0, 0.0, np.where(tr < L, _step(ui, 0), np.where(
        tr < t_out, 1.0, np.where(tr < t_out + L, _step(1 - uo, 0), 0.0))))
    r2 = np.where(ramp_in, _step(ui, 1) / L, np.where(ramp_out, -_step(1 - uo, 1) / L, 0.0))
    r3 = np.where(ramp_in, _step(ui, 2) / L**2, np.where(ramp_out, _step(1 - uo, 2) / L**2, 0.0))
    p0, p1, p2, p3 = (evaluate(plan.path, sigma, k) for k in range(4))
    a, b, c = rate[:, None], r2[:, None], r3[:, None]
    pos[:, :2] += p0
    vel[:, :2] += p1 * a
    acc[:, :2] += p2 * a**2 + p1 * b
    jerk[:, :2] += p3 * a**3 + 3 * p2 * a * b + p1 * c
    return TrajectorySample(t, pos, vel, acc, jerk, np.zeros((n, 3)))


# ------------------------------------------------------------------------- control law
def desired_acceleration(pos: np.ndarray, vel: np.ndarray, ref: TrajectorySample,
                         ff: np.ndarray, side: PDGains, alt: PDGains, hover: float) -> np.ndarray:
    """Acceleration (NED, m/s^2, shape ``(3,)``) the outer PDs ask for, feed-forward ``ff`` added.

    ``ref`` holds one sample; ``ff`` is the feed-forward acceleration (NED).
    """
    e = ref.pos_m[0] - pos
    ev = ref.vel_m_s[0] - vel
    k = np.array([G_M_S2, G_M_S2, G_M_S2 / hover])
    kc = np.array([side.Kc, side.Kc, alt.Kc])
    kd = np.array([side.Kd, side.Kd, alt.Kd])
    return np.asarray(k * (kc * e + kd * ev) + ff)


def attitude_from_acceleration(acc_ned: np.ndarray, yaw_rad: float, hover: float,
                               max_tilt_rad: float) -> tuple[tuple[float, float, float, float],
                                                               float]:
    """Attitude quaternion (w, x, y, z) and normalised thrust for a desired acceleration.

    Paper eq. 3-7 in NED: specific force ``f = a - g e_down``; body z along ``-f``; body y
    perpendicular to it and the heading ``(cos yaw, sin yaw, 0)``; thrust ``hover |f| / g``.
    The tilt is limited to ``max_tilt_rad`` by shortening the horizontal force.

    Examples
    --------
    >>> q, thr = attitude_from_acceleration(np.zeros(3), 0.0, 0.5, 0.6)
    >>> [round(v, 6) + 0.0 for v in q], round(thr, 6)
    ([1.0, 0.0, 0.0, 0.0], 0.5)
    """
    f = np.asarray(acc_ned, dtype=float) - np.array([0.0, 0.0, G_M_S2])
    up = max(-f[2], 0.1 * G_M_S2)  # never ask for thrust pointing down
    fh = f[:2]
    lim = up * math.tan(max_tilt_rad)
    nh = float(np.hypot(*fh))
    if nh > lim:
        fh = fh * (lim / nh)
    f = np.array([fh[0], fh[1], -up])
    mag = float(np.linalg.norm(f))
    zb = -f / mag
    xc = np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0])
    yb = np.cross(zb, xc)
    yb /= np.linalg.norm(yb)
    xb = np.cross(yb, zb)
    R = np.column_stack([xb, yb, zb])
    return _quat_from_matrix(R), min(max(hover * mag / G_M_S2, 0.0), 1.0)


def _quat_from_matrix(R: np.ndarray) -> tuple[float, float, float, float]:
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, float(R[2, 1] - R[1, 2]) / s, float(R[0, 2] - R[2, 0]) / s,
             float(R[1, 0] - R[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = float(R[j, i] + R[i, j]) / s
        v[k] = float(R[k, i] + R[i, k]) / s
        q = (float(R[k, j] - R[j, k]) / s, v[0], v[1], v[2])
    sign = 1.0 if q[0] >= 0 else -1.0
    return (sign * q[0], sign * q[1], sign * q[2], sign * q[3])


@dataclass(frozen=True)
class _FeedForward:
    """Per-axis model feed-forward: ``u = (T a + v) / K`` at ``t + lead``; gain to acceleration."""

    lead_s: np.ndarray  # (3,)
    T_s: np.ndarray  # (3,)
    K: np.ndarray  # (3,), nan where no model: plain acceleration feed-forward
    to_acc: np.ndarray  # (3,): g, g, g/hover

    def accel(self, plan: FlightPlan, t_s: float) -> tuple[TrajectorySample, np.ndarray]:
        """The reference at ``t_s`` (one sample) and the feed-forward acceleration (NED)."""
        r = flight_reference(plan, np.concatenate([[t_s], t_s + self.lead_s]))
        out = np.array(r.acc_m_s2[0], dtype=float)
        for i in range(3):
            if np.isfinite(self.K[i]):
                a, v = r.acc_m_s2[1 + i, i], r.vel_m_s[1 + i, i]
                out[i] = self.to_acc[i] * (self.T_s[i] * a + v) / self.K[i]
        now = TrajectorySample(r.t_s[:1], r.pos_m[:1], r.vel_m_s[:1], r.acc_m_s2[:1],
                               r.jerk_m_s3[:1], r.snap_m_s4[:1])
        return now, out

    def describe(self) -> str:
        if not np.any(np.isfinite(self.K)):
            return "reference acceleration (no loop models given)"
        parts = []
        for i, axis in enumerate(("x", "y", "altitude")):
            if np.isfinite(self.K[i]):
                parts.append(f"{axis}: (T {self.T_s[i]:.3f} s a + v)/K {self.K[i]:.3g}, "
                             f"{self.lead_s[i] * 1e3:.0f} ms ahead")
            else:
                parts.append(f"{axis}: reference acceleration")
        return "model inverse; " + "; ".join(parts)


def feedforward_leads(models: Mapping[str, Mapping[str, float]],
                      gains: Mapping[Loop, PDGains], period_s: float) -> dict[str, float]:
    """Look-ahead (s) of the model feed-forward per axis: delay plus closed-inner-loop lag.

    ``x`` uses the pitch loop, ``y`` the roll loop; the lag is the phase delay of the closed
    attitude loop ``Kc G / (1 + (Kc + Kd s) G)`` at the lap frequency ``2 pi / period_s``.
    Axes whose models are missing are left out.
    """
    w = np.array([2 * math.pi / period_s])
    out: dict[str, float] = {}
    for axis, inner, loop in (("x", "pitch", Loop.PITCH), ("y", "roll", Loop.ROLL)):
        if axis in models:
            lag = 0.0
            if inner in models and loop in gains:
                m, g = models[inner], gains[loop]
                G = inner_response(m["K"], m["T_prop"], m["T1"], m["tau"], w)
                lag = float(-np.angle(closed_inner_response(g.Kc, g.Kd, G, w)[0, 0]) / w[0])
            out[axis] = float(models[axis]["tau"]) + lag
    if "altitude" in models:
        m = models["altitude"]
        out["altitude"] = float(m["tau"]) + float(m["T_prop"])
    return out


def _feedforward(models: Mapping[str, Mapping[str, float]] | None, gains: Mapping[Loop, PDGains],
                 period_s: float, hover: float) -> _FeedForward:
    nan = float("nan")
    lead, T, K = np.zeros(3), np.zeros(3), np.full(3, nan)
    if models:
        leads = feedforward_leads(models, gains, period_s)
        for i, (axis, tkey) in enumerate((("x", "T2"), ("y", "T2"), ("altitude", "T1"))):
            if axis in models:
                lead[i], T[i], K[i] = leads[axis], models[axis][tkey], models[axis]["K"]
    return _FeedForward(lead, T, K, np.array([G_M_S2, G_M_S2, G_M_S2 / hover]))


# ------------------------------------------------------------------------- errors
@dataclass(frozen=True)
class TrackingErrors:
    """Position error statistics over the measured window (m). Axes: north, east, down."""

    mean_m: float
    max_m: float
    rms_m: float
    axis_mean_m: tuple[float, float, float]
    axis_max_m: tuple[float, float, float]
    samples: int
    rate_hz: float


def tracking_errors(t_s: np.ndarray, pos_m: np.ndarray, ref_m: np.ndarray) -> TrackingErrors:
    """Euclidean and per-axis error of ``pos_m`` against ``ref_m`` (both ``(n, 3)``)."""
    e = np.asarray(pos_m) - np.asarray(ref_m)
    if len(e) < 2:
        raise SafetyAbort("too few position reports in the measured laps: check the link "
                          "and that LOCAL_POSITION_NED streams")
    norm = np.linalg.norm(e, axis=1)
    span = float(t_s[-1] - t_s[0])
    return TrackingErrors(
        mean_m=float(norm.mean()), max_m=float(norm.max()),
        rms_m=float(np.sqrt(np.mean(norm**2))),
        axis_mean_m=tuple(float(v) for v in np.abs(e).mean(axis=0)),  # type: ignore[arg-type]
        axis_max_m=tuple(float(v) for v in np.abs(e).max(axis=0)),  # type: ignore[arg-type]
        samples=len(e), rate_hz=(len(e) - 1) / span if span > 0 else 0.0)


@dataclass(frozen=True)
class VerifyResult:
    """Outcome of a figure-eight check. Arrays cover the whole flight (``(n,)`` and ``(n, 3)``).

    ``errors`` holds the measured laps only (``in_window`` marks them).
    """

    connection: str
    profile: str
    size_m: tuple[float, float]
    period_s: float
    laps: int
    errors: TrackingErrors
    gains: Mapping[str, PDGains]
    params: Mapping[str, float]
    feedforward: str
    method: str
    t_s: np.ndarray
    pos_m: np.ndarray
    ref_m: np.ndarray
    in_window: np.ndarray
    duration_s: float
    notes: tuple[str, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no time series)."""
        e = self.errors
        return {
            "schema": "mrft-gcs/verify-1",
            "connection": self.connection, "profile": self.profile,
            "trajectory": {"kind": "figure8-min-snap", "size_m": list(self.size_m),
                           "period_s": self.period_s, "laps_measured": self.laps},
            "error_m": {"mean": e.mean_m, "max": e.max_m, "rms": e.rms_m,
                        "axis_mean": dict(zip("xyz", e.axis_mean_m, strict=True)),
                        "axis_max": dict(zip("xyz", e.axis_max_m, strict=True))},
            "samples": e.samples, "sample_rate_hz": e.rate_hz,
            "gains": {k: {"Kc": g.Kc, "Kd": g.Kd} for k, g in self.gains.items()},
            "parameters": dict(self.params), "feedforward": self.feedforward,
            "method": self.method, "duration_s": self.duration_s, "notes": list(self.notes),
        }


def load_models(report_path: str | Path) -> dict[str, dict[str, float]]:
    """Loop models from a tuning report (``loops.<loop>.model``), for feed-forward.

    Raises
    ------
    InputFileError
        Unreadable file, not JSON, or no loop with a model in it.
    """
    try:
        data = json.loads(Path(report_path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise InputFileError(f"cannot read tuning report {report_path}: {err}") from None
    loops = data.get("loops") if isinstance(data, dict) else None
    out: dict[str, dict[str, float]] = {}
    need = {"x": ("K", "T2", "tau"), "y": ("K", "T2", "tau"), "roll": ("K", "T_prop", "T1", "tau"),
            "pitch": ("K", "T_prop", "T1", "tau"), "altitude": ("K", "T_prop", "T1", "tau")}
    for name, keys in need.items():
        model = (loops or {}).get(name, {}).get("model") if isinstance(loops, dict) else None
        if isinstance(model, dict) and all(isinstance(model.get(k), int | float) for k in keys):
            values = {k: float(model[k]) for k in keys}
            if all(math.isfinite(v) and v >= 0 for v in values.values()) and values["K"] > 0:
                out[name] = values
    if not out:
        raise InputFileError(f"{report_path} holds no loop models (loops.<loop>.model): "
                             "give the JSON report a tune wrote (--report)")
    return out


# ------------------------------------------------------------------------- gains of reference
def reference_gains(vehicle: str | Any) -> dict[Loop, PDGains]:
    """ISE-optimal PD gains (PM >= 20 deg) of a SITL airframe's *true* linear models.

    A well-tuned reference to compare tuned gains with. ``vehicle`` is a bundled name or an
    :class:`~mrft_gcs.sitl.Airframe`. x uses the closed pitch loop, y the closed roll loop.
    """
    af = load_airframe(vehicle) if isinstance(vehicle, str) else vehicle
    lm = af.linear_models()
    out: dict[Loop, PDGains] = {}
    for loop in (Loop.ROLL, Loop.PITCH, Loop.ALTITUDE):
        m = lm[loop.value]
        w = frequency_grid(m["T_prop"], m["T1"], m["tau"])
        d = optimal_pd(inner_response(1, m["T_prop"], m["T1"], m["tau"], w)[0], w)
        out[loop] = PDGains(d.pd.Kc / m["K"], d.pd.Kd / m["K"])
    for loop, inner in ((Loop.X, Loop.PITCH), (Loop.Y, Loop.ROLL)):
        m, s, g = lm[inner.value], lm[loop.value], out[inner]
        w = frequency_grid(m["T_prop"], m["T1"], m["tau"], n=2000, extra_T=(s["T2"], s["tau"]))
        G = closed_inner_response(g.Kc, g.Kd, inner_response(
            m["K"], m["T_prop"], m["T1"], m["tau"], w), w) * side_response(1, s["T2"], s["tau"], w)
        d = optimal_pd(G[0], w)
        out[loop] = PDGains(d.pd.Kc / s["K"], d.pd.Kd / s["K"])
    return out


def reference_params(vehicle: str | Any, profile: str | AutopilotProfile = "sitl",
                     scale: float = 1.0) -> dict[str, float]:
    """Parameter values of :func:`reference_gains` for ``profile`` (gains times ``scale``).

    Uses the hover thrust the SITL reports (the true one, rounded to 0.01).
    """
    af = load_airframe(vehicle) if isinstance(vehicle, str) else vehicle
    prof = load_profile(profile) if isinstance(profile, str) else profile
    gains = {k: PDGains(g.Kc * scale, g.Kd * scale) for k, g in reference_gains(af).items()}
    return gains_to_params(prof, gains, round(af.hover_thrust, 2))


# ------------------------------------------------------------------------- flying
class _Shared:
    """Latest vehicle state: written by the telemetry loop, read by the setpoint thread."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.t_s: float | None = None  # vehicle clock of the last position report
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.yaw: float | None = None
        self.t0: float | None = None  # vehicle time at which control starts


def _read_gains(link: Any, prof: AutopilotProfile) -> tuple[dict[Loop, PDGains], dict[str, float]]:
    client = ParamClient(link)
    values = {n: p.value for n, p in client.read_many(prof.parameter_names()).items()}
    gains = _params_to_gains(prof, values)
    for loop in (Loop.X, Loop.ALTITUDE, Loop.ROLL, Loop.PITCH):
        g = gains.get(loop)
        if g is None or not (g.Kc > 0 and g.Kd > 0):
            raise UsageError(f"the vehicle's {loop.value} gains are missing or not positive "
                             f"({g}): tune it first ('mrft-tune tune') or check --profile")
    return gains, values


def verify_figure8(connection: str | Any, size_m: tuple[float, float] = (2.0, 1.0),
                   period_s: float = 5.5, laps: int = 2, profile: str = "sitl", *,
                   settle_laps: int = 1, altitude_m: float = 1.0,
                   models: Mapping[str, Mapping[str, float]] | None = None,
                   record_hz: float = 250.0, land: bool = True, timeout_s: float = 5.0,
                   progress: Callable[[str, float], None] | None = None) -> VerifyResult:
    """Fly the minimum-snap figure-eight on the vehicle's current gains and measure the error.

    Parameters
    ----------
    connection : str or VehicleLink
        A connection string (opened and closed here) or an open link (left open).
    size_m : (W, H)
        Figure size (m): W north, H east. The paper's benchmark: 2 x 1 m in 5.5 s.
    period_s : float
        Time of one lap (s).
    laps : int
        Laps measured, after ``settle_laps`` unmeasured ones and the ramp-in.
    profile : str
        Autopilot profile: which parameters hold the gains, which mode numbers to use.
    altitude_m : float
        Take-off height of the figure above the start (ignored if already flying).
    models : mapping, optional
        Loop models for the attitude feed-forward, keyed ``x``, ``y``, ``roll``, ``pitch``,
        ``altitude`` as in the tune report (``loops.*.model``) or
        :meth:`~mrft_gcs.sitl.Airframe.linear_models`.
    record_hz : float
        Rate asked for ATTITUDE and LOCAL_POSITION_NED (>= 100 Hz).
    land : bool
        Land at the end (else hold in the position mode).
    progress : callable, optional
        ``f(phase, fraction)`` called as the flight goes.

    Raises
    ------
    UsageError
        Bad arguments, a figure that exceeds the profile's distance limit, missing gains.
    LinkError
        No vehicle, refused mode or arming.
    SafetyAbort
        Tilt, altitude or distance limit, telemetry loss, Ctrl-C, or the vehicle leaving
        OFFBOARD; a landing was commanded.
    """
    prof = load_profile(profile)
    if record_hz < 100:
        raise UsageError(f"record at 100 Hz or more, got {record_hz:g} Hz")
    W, H = (float(v) for v in size_m)
    lim = prof.safety
    if max(W, H) / 2 + 0.5 > lim.max_distance_m:
        raise UsageError(f"a {W:g} x {H:g} m figure does not fit the profile's "
                         f"{lim.max_distance_m:g} m distance limit: fly a smaller one")
    own = isinstance(connection, str)
    link: VehicleLink
    if isinstance(connection, str):
        link = VehicleLink.connect(connection, timeout_s=timeout_s)
    else:
        link = connection
    try:
        if link.family is AutopilotFamily.ARDUPILOT:
            raise UsageError("verify flies SET_ATTITUDE_TARGET with raw thrust (PX4 OFFBOARD); "
                             "on ArduPilot that needs GUIDED_NOGPS with GUID_OPTIONS bit 3, "
                             "which this version does not drive")
        link.modes = dict(prof.modes)
        gains, values = _read_gains(link, prof)
        hover = values[prof.altitude.hover_thrust]
        for msg in ("ATTITUDE", "LOCAL_POSITION_NED"):
            link.request_message_interval(msg, record_hz)
        return _fly(link, prof, gains, values, hover, (W, H), period_s, laps, settle_laps,
                    altitude_m, models, land, progress)
    finally:
        if own:
            link.close()


def _fly(link: Any, prof: AutopilotProfile, gains: dict[Loop, PDGains], values: dict[str, float],
         hover: float, size_m: tuple[float, float], period_s: float, laps: int, settle_laps: int,
         altitude_m: float, models: Mapping[str, Mapping[str, float]] | None, land: bool,
         progress: Callable[[str, float], None] | None) -> VerifyResult:
    lim = prof.safety
    shared = _Shared()
    link.drain()  # queued telemetry is old: the plan starts from where the vehicle is now
    # where are we, and which way do we face
    deadline = time.monotonic() + 5.0
    while (shared.t_s is None or shared.yaw is None) and time.monotonic() < deadline:
        s = link.next_sample(0.5)
        if isinstance(s, LocalPosition):
            shared.t_s = s.t_s
            shared.pos = np.array([s.x_m, s.y_m, s.z_m])
        elif isinstance(s, Attitude):
            shared.yaw = s.yaw_rad
    if shared.t_s is None or shared.yaw is None:
        raise LinkError("no LOCAL_POSITION_NED and ATTITUDE from the vehicle within 5 s: "
                        "it needs a position estimate (GPS or motion capture) to fly the check")
    airborne = link.heartbeat.armed and -shared.pos[2] > 0.2
    start = (float(shared.pos[0]), float(shared.pos[1]), float(shared.pos[2]))
    plan = plan_figure8(start, airborne=airborne, size_m=size_m, period_s=period_s,
                        laps=laps, settle_laps=settle_laps, altitude_m=altitude_m)
    if -plan.centre_ned_m[2] > lim.max_altitude_m:
        raise UsageError(f"the figure at {-plan.centre_ned_m[2]:.1f} m is above the profile's "
                         f"{lim.max_altitude_m:g} m altitude limit")
    ff = _feedforward(models, gains, period_s, hover)
    side, alt = gains[Loop.X], gains[Loop.ALTITUDE]
    yaw = float(shared.yaw)
    max_tilt = math.radians(lim.max_tilt_deg)

    def setpoint(_wall_s: float) -> Any:
        with shared.lock:
            t, t0, pos, vel = shared.t_s, shared.t0, shared.pos.copy(), shared.vel.copy()
        if t is None or t0 is None:  # armed on the ground, not flying yet: idle
            return AttitudeTarget(0.0, _quat_from_matrix(_yaw_matrix(yaw)), 0.0)
        ref, acc_ff = ff.accel(plan, t - t0)
        acc = desired_acceleration(pos, vel, ref, acc_ff, side, alt, hover)
        q, thrust = attitude_from_acceleration(acc, yaw, hover, max_tilt)
        return AttitudeTarget(t, q, thrust)

    rec_t: list[float] = []
    rec_p: list[tuple[float, float, float]] = []
    offboard = prof.modes["offboard"]
    streamer = SetpointStreamer(link, setpoint, rate_hz=250.0)
    home = np.array(plan.start_ned_m)
    try:
        if airborne:  # fly from where it hovers at once: OFFBOARD takes over mid-air
            shared.t0 = shared.t_s
        streamer.start()
        time.sleep(0.1)  # PX4 takes OFFBOARD only once setpoints stream
        link.set_mode(offboard)
        if not link.heartbeat.armed:
            link.arm()
        if not airborne:  # on the ground: idle until armed, then the clock starts
            link.drain()
            first = _next_position(link)
            with shared.lock:
                shared.t_s, shared.t0 = first.t_s, first.t_s
                shared.pos = np.array([first.x_m, first.y_m, first.z_m])
        t0 = float(shared.t0)  # type: ignore[arg-type]
        t_end = t0 + plan.duration_s
        last_report = -1.0
        seen_offboard = False
        while True:
            streamer.raise_if_aborted()
            s = link.next_sample(0.5)
            if isinstance(s, LocalPosition):
                p = np.array([s.x_m, s.y_m, s.z_m])
                with shared.lock:
                    shared.t_s, shared.pos = s.t_s, p
                    shared.vel = np.array([s.vx_m_s, s.vy_m_s, s.vz_m_s])
                rec_t.append(s.t_s)
                rec_p.append((s.x_m, s.y_m, s.z_m))
                if float(np.hypot(*(p[:2] - home[:2]))) > lim.max_distance_m:
                    raise SafetyAbort(f"{np.hypot(*(p[:2] - home[:2])):.1f} m from the start, "
                                      f"beyond the {lim.max_distance_m:g} m limit")
                if -p[2] > lim.max_altitude_m + 0.5:
                    raise SafetyAbort(f"altitude {-p[2]:.1f} m beyond the "
                                      f"{lim.max_altitude_m:g} m limit")
                if progress is not None and s.t_s - last_report > 0.25:
                    last_report = s.t_s
                    progress("figure-eight", min((s.t_s - t0) / plan.duration_s, 1.0))
                if s.t_s >= t_end:
                    break
            elif isinstance(s, Attitude):
                tilt = math.degrees(math.acos(max(-1.0, min(1.0, math.cos(s.roll_rad)
                                                                * math.cos(s.pitch_rad)))))
                if tilt > lim.max_tilt_deg + 10.0:
                    raise SafetyAbort(f"tilt {tilt:.0f} deg beyond the {lim.max_tilt_deg:g} deg "
                                      "limit (+10 deg margin for tracking)")
            elif isinstance(s, Heartbeat):
                # heartbeats queued before the switch still show the old mode
                in_offboard = mode_matches(link.family, offboard, s.custom_mode)
                seen_offboard = seen_offboard or in_offboard
                if seen_offboard and not in_offboard:
                    raise SafetyAbort("the vehicle left OFFBOARD during the check (failsafe or "
                                      "pilot): check the link and the vehicle's messages")
            elif s is None and link.telemetry_age_s() > 1.0:
                streamer.raise_if_aborted()
                raise SafetyAbort("telemetry lost during the check")
    except (SafetyAbort, LinkError, KeyboardInterrupt) as err:
        streamer.stop()
        try:
            link.land(wait_ack=False)
        except LinkError:
            pass
        if isinstance(err, KeyboardInterrupt):
            raise SafetyAbort("interrupted (Ctrl-C): landing commanded") from None
        if isinstance(err, SafetyAbort) and "landing" not in str(err):
            raise SafetyAbort(f"{err}; landing commanded") from None
        raise
    notes: list[str] = []
    if land:
        link.land()
        streamer.stop()
        if not _wait_disarmed(link, 30.0):
            notes.append("landing commanded; the vehicle had not disarmed 30 s later")
    else:
        link.set_mode(prof.modes["position"])
        streamer.stop()
        notes.append(f"left holding position in {prof.modes['position'].name}")
    t = np.asarray(rec_t) - t0
    pos = np.asarray(rec_p).reshape(-1, 3)
    ref = flight_reference(plan, t).pos_m
    w0, w1 = plan.window_s
    inside = (t >= w0) & (t <= w1)
    errors = tracking_errors(t[inside], pos[inside], ref[inside])
    stats = streamer.stats()
    if stats.skipped:
        notes.append(f"setpoint stream: {stats.line()}")
    used = {"x": gains[Loop.X], "y": gains[Loop.Y], "altitude": gains[Loop.ALTITUDE],
            "roll": gains[Loop.ROLL], "pitch": gains[Loop.PITCH]}
    method = (f"GCS-side position/altitude PD (x, y: Kc {side.Kc:.3g} rad/m, Kd {side.Kd:.3g} "
              f"rad/(m/s); altitude: Kc {alt.Kc:.3g} /m, Kd {alt.Kd:.3g} s/m, hover thrust "
              f"{hover:.3g}) + feed-forward -> attitude and thrust (paper eq. 3-7) as "
              f"SET_ATTITUDE_TARGET in {offboard.name} at 250 Hz; the onboard attitude loop "
              f"flies it on the vehicle's MC_* gains (roll Kc {gains[Loop.ROLL].Kc:.3g}, "
              f"Kd {gains[Loop.ROLL].Kd:.3g}; pitch Kc {gains[Loop.PITCH].Kc:.3g}, "
              f"Kd {gains[Loop.PITCH].Kd:.3g}). Error: reported position (LOCAL_POSITION_NED) "
              f"against the reference at the report's timestamp, {laps} whole laps after "
              f"{settle_laps} settling lap(s).")
    return VerifyResult(
        connection=link.spec.text, profile=prof.name, size_m=size_m, period_s=period_s,
        laps=laps, errors=errors, gains=used, params=dict(values), feedforward=ff.describe(),
        method=method, t_s=t, pos_m=pos, ref_m=ref, in_window=inside,
        duration_s=plan.duration_s, notes=tuple(notes))


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _next_position(link: Any, timeout_s: float = 2.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = link.next_sample(0.2)
        if isinstance(s, LocalPosition):
            return s
    raise SafetyAbort(f"no LOCAL_POSITION_NED for {timeout_s:g} s after arming")


def _wait_disarmed(link: Any, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = link.next_sample(0.5)
        if isinstance(s, Heartbeat) and not s.armed:
            return True
    return False


# ------------------------------------------------------------------------- rendering
def plot_verify(result: VerifyResult, path: str | Path) -> Path:
    """PNG: top view (reference vs flown) and the time profiles of x, y, z."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is a core dependency
        raise MissingDependency("plots need matplotlib: pip install matplotlib") from None
    t, p, r, w = result.t_s, result.pos_m, result.ref_m, result.in_window
    fig = plt.figure(figsize=(11, 7.5), layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=(1.1, 1))
    top = fig.add_subplot(grid[:, 0])
    top.plot(r[w, 1], r[w, 0], "k--", lw=1.2, label="reference")
    top.plot(p[w, 1], p[w, 0], "C0", lw=1.0, label="flown (measured laps)")
    top.set_xlabel("east (m)")
    top.set_ylabel("north (m)")
    top.set_aspect("equal", "datalim")
    top.legend(loc="upper right")
    e = result.errors
    top.set_title(f"{result.size_m[0]:g} x {result.size_m[1]:g} m, {result.period_s:g} s: mean "
                  f"{e.mean_m * 100:.1f} cm, max {e.max_m * 100:.1f} cm")
    if np.any(w):
        t0, t1 = t[w][0], t[w][-1]
    else:
        t0 = t1 = 0.0
    for i, name in enumerate(("north x (m)", "east y (m)", "down z (m)")):
        ax = fig.add_subplot(grid[i, 1])
        ax.plot(t, r[:, i], "k--", lw=1.0)
        ax.plot(t, p[:, i], "C0", lw=0.9)
        ax.axvspan(t0, t1, color="C2", alpha=0.08)
        ax.set_ylabel(name)
        if i == 2:
            ax.set_xlabel("time since start of control (s); shaded: measured laps")
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
