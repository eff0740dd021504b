"""Entry points a tune calls: identify a loop from the steady cycles its relay test recorded.

A live tune (:mod:`mrft_gcs.flight.api`), a replay (:mod:`mrft_gcs.dryrun`) and the
identification worker (:mod:`mrft_gcs.identify.worker`) all call these, on a
:class:`RelayRecord` (the flight sequence's ``CycleSnapshot`` is one).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from mrft_gcs.errors import IdentificationError
from mrft_gcs.identify.closed_loop import closed_attitude_identification
from mrft_gcs.identify.result import Identification, RelaySettings
from mrft_gcs.identify.runtime import identify, relay_settings
from mrft_gcs.loops import Loop, LoopKind
from mrft_gcs.plant import InnerModel, closed_inner_response, inner_response

__all__ = ["Identifier", "RelayRecord", "bundled_identifier", "closed_loop_summary",
           "measured_attitude_loop", "synthetic_cycles", "warm_up_identification"]


class RelayRecord(Protocol):
    """The steady cycles of one relay test (arrays of shape (m,)), as identification reads them."""

    @property
    def loop(self) -> Loop: ...
    @property
    def t_s(self) -> np.ndarray: ...  # time, s
    @property
    def u(self) -> np.ndarray: ...  # relay output, with its bias
    @property
    def y(self) -> np.ndarray: ...  # measured variable
    @property
    def beta(self) -> float: ...
    @property
    def h(self) -> float: ...
    @property
    def bias(self) -> float: ...
    @property
    def setpoint(self) -> float | None: ...  # None: the set point moves (roll, pitch)
    @property
    def tilt(self) -> np.ndarray | None: ...  # x, y: measured tilt along the axis, rad


#: ``f(loop, record, inner_identification) -> Identification``
Identifier = Callable[[Loop, RelayRecord, Identification | None], Identification]


def bundled_identifier(loop: Loop, snap: RelayRecord,
                       inner: Identification | None = None) -> Identification:
    """Identification with the bundled classifiers (:func:`mrft_gcs.identify.identify`)."""
    return identify(loop.kind, snap.t_s, snap.u, snap.y, beta=snap.beta, h=snap.h,
                    bias=snap.bias, inner=inner, setpoint=snap.setpoint, tilt=snap.tilt)


def measured_attitude_loop(snap: RelayRecord) -> Identification:
    """The autopilot's closed attitude loop behind a side relay (attitude path).

    Measured from the record's commanded and measured tilt at the relay's odd
    harmonics and expressed as an equivalent attitude model and PD
    (:func:`mrft_gcs.identify.closed_loop.closed_attitude_identification`), the
    ``inner`` the side identification takes.

    Raises
    ------
    IdentificationError
        No tilt record, or no equivalent loop follows the points.
    """
    if snap.tilt is None:
        raise IdentificationError(
            f"{snap.loop.value}: no measured tilt over the side relay cycles (ATTITUDE "
            f"must stream with LOCAL_POSITION_NED); cannot measure the attitude loop")
    return closed_attitude_identification(snap.t_s, snap.u, snap.tilt, beta=snap.beta,
                                          h=snap.h)


def closed_loop_summary(inner: Identification, side: Loop) -> str:
    """One line on a measured closed attitude loop: bandwidth, response at the test."""
    m, g, pts = inner.model, inner.gains, inner.diagnostics.measured
    assert isinstance(m, InnerModel) and pts is not None  # a closed attitude loop
    w = np.logspace(-1, 3, 400)
    T = closed_inner_response(g.Kc, g.Kd, inner_response(m.K, m.T_prop, m.T1, m.tau, w),
                              w)[0]
    below = np.flatnonzero(np.abs(T) < 1 / math.sqrt(2))
    bw = f"{w[below[0]]:.3g} rad/s" if below.size else "above 1000 rad/s"
    w0, t0 = float(pts.w[0]), complex(pts.T[0])
    return (f"its closed loop was measured during the {side.value} relay at {len(pts.w)} "
            f"harmonics: gain {abs(t0):.3f} and phase {math.degrees(np.angle(t0)):.1f} deg at "
            f"{w0:.3g} rad/s, bandwidth (-3 dB) {bw}, fit within {pts.rms_sd:.2g} "
            f"standard errors")


def synthetic_cycles(period_s: float, h: float, amplitude: float, n: int = 6,
                     dt: float = 0.004) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A square relay output and a lagging triangle wave: enough to run identification."""
    t = np.arange(0.0, n * period_s, dt)
    ph = 2 * np.pi * t / period_s
    u = h * np.sign(np.sin(ph) + 1e-12)
    y = -amplitude * (2 / np.pi) * np.arcsin(np.sin(ph - np.pi / 2 - 0.3))
    return t, u, y


def warm_up_identification(attitude: RelaySettings, altitude: RelaySettings) -> float:
    """Run the bundled identification once on synthetic cycles; returns the seconds taken.

    The first identification of each kind imports and loads what it needs (the side
    classifiers and the harmonic fit: about a second on a 2-core machine). In flight
    that work holds the interpreter next to the 250 Hz setpoint stream (measured: a
    51 ms gap in the stream, and x/y started 0.7 s after altitude was tuned), so it
    is done on the ground, before the stream starts. The results are thrown away and
    errors are ignored: nothing but loading happens here.
    """
    t0 = time.monotonic()
    try:
        t, u, y = synthetic_cycles(0.3, 0.12, 0.05)
        inner = identify(LoopKind.ATTITUDE, t, u, y, beta=attitude.beta, h=0.12)
        t, u, y = synthetic_cycles(0.75, 0.1, 0.04)
        identify(LoopKind.ALTITUDE, t, u + 0.5, y, beta=altitude.beta, h=0.1, bias=0.5,
                 setpoint=0.0)
        side = relay_settings(LoopKind.SIDE, inner)
        t, u, y = synthetic_cycles(1.0, 0.16, 0.04)
        identify(LoopKind.SIDE, t, u, y, beta=side.beta, h=0.16, inner=inner, setpoint=0.0)
    except Exception:  # noqa: BLE001 - loading only: the flight's own calls report errors
        pass
    return time.monotonic() - t0
