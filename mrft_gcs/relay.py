"""Relay controllers: the MRFT (paper eq. 9) and the bounding controller (eq. 22).

Both are streaming classes with ``reset()`` and ``step()``. Their state is held
in numpy arrays so one object drives ``n`` independent loops at once: the
offline simulator steps thousands of processes together, the live tuner steps
one (``n = 1``). The same code runs in both, so training data and flight data
come from the very same relay.

MRFT as implemented
-------------------
The paper writes the law as ``u = +h`` when ``e >= b1`` or (``e > -b2`` and
``u- = +h``), ``u = -h`` when ``e <= -b2`` or (``e < b1`` and ``u- = -h``), with
``b1 = -beta e_min`` and ``b2 = beta e_max``, the extremes of the error after
its last zero crossing. Read literally the two branches overlap for
``beta < 0`` (the thresholds swap sides of zero), so it is implemented as the
state machine it describes:

- in the ``+h`` state, ``e_max`` is the largest error since entering the state
  (it becomes positive once the error has crossed zero); the relay switches to
  ``-h`` when ``e <= -beta e_max``, once armed;
- in the ``-h`` state, symmetrically with ``e_min``: switch to ``+h`` when
  ``e >= -beta e_min``, once armed.

``band`` (default 0) is a noise band: a state is armed only when the switch
threshold lies more than ``band`` from the extreme, ``|e_ext| (1 + beta) >
band``, so measurement noise cannot fire a switch when ``beta < 0`` (where the
threshold sits between the extreme and zero). Strong leads (``beta`` near -1)
therefore need an amplitude of ``band / (1 + beta)``; with the noise bands used
here that is why the tests stay at ``beta >= -0.7``. (A floor on ``1 + beta``
was tried: it let noise fire switches on slow processes, measured.) Until the first
switch the relay is a plain sign relay (``e_max = e_min = 0``, as the paper starts it) whose switch
also waits for the error to leave the band.

One guard keeps noise from stranding the relay: while a state is not yet
armed, an error that moves *away* from arming by more than the band (below
its value at entry in the ``+h`` state, above it in the ``-h`` state) means the
last switch was triggered by noise before the plant turned, so the relay
switches back. In a clean cycle the error keeps moving towards arming after a
switch, so the guard never fires. In steady
oscillation this is exactly eq. 9, and its describing function is
``4h/(pi a) (sqrt(1 - beta^2) - j beta)`` (eq. 11).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MRFT", "BoundingRelay", "mrft_phase_deg", "beta_for_phase"]


def mrft_phase_deg(beta: float) -> float:
    """Phase (deg) the MRFT adds: ``arcsin(-beta)``; negative ``beta`` is a lead."""
    return float(np.degrees(np.arcsin(-beta)))


def beta_for_phase(phi_deg: float) -> float:
    """Inverse of :func:`mrft_phase_deg`."""
    return float(-np.sin(np.radians(phi_deg)))


class MRFT:
    """Modified relay (eq. 9), vectorised over ``n`` loops.

    Parameters
    ----------
    beta : float or array (n,)
        MRFT parameter in (-1, 1); ``arcsin(beta)`` is the phase of eq. 10.
    h : float or array (n,)
        Relay amplitude (loop input units).
    bias : float or array (n,)
        Constant added to the output: ``u = bias +- h``.
    band : float or array (n,)
        Noise band on the error excursions (loop output units), see module doc.
    n : int, optional
        Number of loops (taken from the array arguments when omitted).

    Examples
    --------
    >>> r = MRFT(beta=-0.3, h=1.0)
    >>> [float(r.step(e)[0]) for e in (0.1, 0.5, 0.2, 0.1)]
    [1.0, 1.0, 1.0, -1.0]
    """

    def __init__(self, beta, h, bias=0.0, band=0.0, n: int | None = None) -> None:
        arrays = [np.atleast_1d(np.asarray(a, dtype=float)) for a in (beta, h, bias, band)]
        size = n if n is not None else max(a.size for a in arrays)
        self.beta, self.h, self.bias, self.band = (np.broadcast_to(a, (size,)).copy()
                                                   for a in arrays)
        if np.any(np.abs(self.beta) >= 1):
            raise ValueError("MRFT beta must lie in (-1, 1)")
        if np.any(self.h <= 0):
            raise ValueError("MRFT amplitude h must be positive")
        self.n = size
        self.reset()

    def reset(self) -> None:
        """Back to the initial state: no switch yet, extremes at zero."""
        self.state = np.zeros(self.n)  # +1 / -1; 0 before the first sample
        self.ext = np.zeros(self.n)  # e_max in the +h state, e_min in the -h state
        self.entry = np.zeros(self.n)  # error when the current state was entered
        self.first = np.ones(self.n, dtype=bool)
        self.switches = np.zeros(self.n, dtype=np.int64)

    def step(self, e) -> np.ndarray:
        """Relay output for the error sample(s) ``e`` (shape ``(n,)`` or scalar)."""
        e = np.broadcast_to(np.asarray(e, dtype=float), (self.n,))
        unset = self.state == 0
        if unset.any():
            self.state[unset] = np.where(e[unset] >= 0, 1.0, -1.0)
            self.entry[unset] = e[unset]
        high = self.state > 0
        band = self.band
        self.ext = np.where(high, np.maximum(self.ext, e), np.minimum(self.ext, e))
        thr = -self.beta * self.ext
        reach = np.abs(self.ext) * (1 + self.beta)  # distance from the extreme to the threshold
        armed_hi = (self.ext > 0) & (reach > band)
        armed_lo = (self.ext < 0) & (reach > band)
        down = high & np.where(self.first, e < -band,
                               (armed_hi & (e <= thr)) | (~armed_hi & (e < self.entry - 2 * band)))
        up = ~high & np.where(self.first, e > band,
                              (armed_lo & (e >= thr)) | (~armed_lo & (e > self.entry + 2 * band)))
        switch = down | up
        if switch.any():
            self.state = np.where(switch, -self.state, self.state)
            self.ext = np.where(switch, np.where(down, np.minimum(e, 0), np.maximum(e, 0)),
                                self.ext)
            self.entry = np.where(switch, e, self.entry)
            self.first &= ~switch
            self.switches += switch
        return self.bias + self.h * self.state


class BoundingRelay:
    """Bounding controller of eq. 22: a hysteresis relay plus a relay with dead band.

    Keeps the vehicle near its take-off point during the inner-loop tests
    without a tuned position loop. Output is ``0``, ``+-h1`` or ``+-(h1 + h2)``.

    Parameters
    ----------
    eps1, eps2 : float
        Position thresholds (m), ``eps1 < eps2`` (Table V: 1 and 2 m).
    h1, h2 : float
        Relay amplitudes (Table V: 0.05 rad each).
    """

    def __init__(self, eps1: float = 1.0, eps2: float = 2.0, h1: float = 0.05, h2: float = 0.05,
                 n: int = 1) -> None:
        if not 0 < eps1 < eps2:
            raise ValueError("bounding relay needs 0 < eps1 < eps2")
        self.eps1, self.eps2, self.h1, self.h2, self.n = eps1, eps2, h1, h2, n
        self.reset()

    def reset(self) -> None:
        self.out = np.zeros(self.n)

    def step(self, e) -> np.ndarray:
        """Output for the position error(s) ``e`` (m)."""
        e = np.broadcast_to(np.asarray(e, dtype=float), (self.n,))
        a, sgn = np.abs(e), np.sign(e)
        idle = self.out == 0
        # Idle until |e| reaches eps1; once engaged it acts as a sign relay (h1) ...
        out = np.where(idle & (a < self.eps1), 0.0, self.h1 * sgn)
        # ... with the dead-band relay adding h2 beyond eps2.
        out = np.where(a >= self.eps2, (self.h1 + self.h2) * sgn, out)
        self.out = out
        return out.copy()
