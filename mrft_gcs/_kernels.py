"""Compiled inner loops of the relay simulations (numba), used when numba is installed.

These are the hot loops of :mod:`mrft_gcs.simulate` written per process as
scalar code. They implement exactly the same relay law and discretisation as
the numpy reference path (``tests/test_simulate.py`` checks the two agree to
rounding), and draw measurement noise from the same table and generator, so a
seed gives the same record with or without numba.
"""

from __future__ import annotations

import numpy as np

__all__ = ["AVAILABLE", "inner_mrft", "side_mrft"]

try:  # numba is optional: the numpy path in simulate.py is the reference.
    from numba import njit

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only without numba
    AVAILABLE = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        def wrap(f):
            return f

        return wrap(args[0]) if args and callable(args[0]) else wrap


@njit(cache=True, inline="always")
def _relay(e, beta, band, state, ext, entry, first):
    """One step of the relay law of :class:`mrft_gcs.relay.MRFT` for one loop."""
    if state == 0.0:
        state = 1.0 if e >= 0 else -1.0
        entry = e
    if state > 0:
        ext = max(ext, e)
        if first:
            sw = e < -band
        elif ext > 0 and ext * (1 + beta) > band:
            sw = e <= -beta * ext
        else:
            sw = e < entry - 2.0 * band
        if sw:
            return -1.0, min(e, 0.0), e, False
    else:
        ext = min(ext, e)
        if first:
            sw = e > band
        elif ext < 0 and -ext * (1 + beta) > band:
            sw = e >= -beta * ext
        else:
            sw = e > entry + 2.0 * band
        if sw:
            return 1.0, max(e, 0.0), e, False
    return state, ext, entry, first


# Knuth's MMIX linear congruential generator, on int64 (wrapping, as two's complement);
# the table index is taken from bits 40..(40+TABLE_BITS) of the state.
LCG_A = 6364136223846793005
LCG_C = 1442695040888963407
_FAST = {"contract", "arcp", "nsz", "afn"}  # FMA and friends; no reassociation


@njit(cache=True, inline="always")
def _lcg(s):
    return s * LCG_A + LCG_C


@njit(cache=True, fastmath=_FAST)
def inner_mrft(Ad, B0, B1, Kr, d, beta, h, bias, band, noise, rng_state, table, steps, keep,
               U, Y):  # pragma: no cover - compiled
    n = Ad.shape[0]
    mask = table.size - 1
    start = steps - keep
    for i in range(n):
        z0 = 0.0
        z1 = 0.0
        z2 = 0.0
        a0, a1, a2 = Ad[i, 0], Ad[i, 1], Ad[i, 2]
        b00, b01, b02 = B0[i, 0], B0[i, 1], B0[i, 2]
        b10, b11, b12 = B1[i, 0], B1[i, 1], B1[i, 2]
        k0, k1, k2 = Kr[i, 0], Kr[i, 1], Kr[i, 2]
        L = d[i] + 2
        buf = np.zeros(L)
        state, ext, entry, first = 0.0, 0.0, 0.0, True
        sd = noise[i]
        s = rng_state[i]
        bi, hi, be, ba = beta[i], h[i], bias[i], band[i]
        w = 0  # write slot of u[k]; u[k-d] sits d slots behind
        for k in range(steps):
            y = k0 * z0 + k1 * z1 + k2 * z2
            if sd > 0:
                s = _lcg(s)
                y += sd * table[(s >> 40) & mask]
            state, ext, entry, first = _relay(-y, bi, ba, state, ext, entry, first)
            u = be + hi * state
            if k >= start:
                U[i, k - start] = u
                Y[i, k - start] = y
            buf[w] = u
            r0 = w - d[i]
            if r0 < 0:
                r0 += L
            r1 = r0 - 1
            if r1 < 0:
                r1 += L
            u0 = buf[r0]
            u1 = buf[r1]
            z0 = a0 * z0 + b00 * u0 + b10 * u1
            z1 = a1 * z1 + b01 * u0 + b11 * u1
            z2 = a2 * z2 + b02 * u0 + b12 * u1
            w += 1
            if w == L:
                w = 0
        rng_state[i] = s


@njit(cache=True, fastmath=_FAST)
def side_mrft(Ad, B0, B1, Kr, Krl, d, Kc, Kd, Sd, S0, S1, Sr, sd_, beta, h, bias, band, noise,
              rng_state, table, steps, keep, U, Y):  # pragma: no cover - compiled
    n = Ad.shape[0]
    mask = table.size - 1
    start = steps - keep
    for i in range(n):
        z = np.zeros(3)
        p = np.zeros(2)
        La = d[i] + 2
        Ls = sd_[i] + 2
        abuf = np.zeros(La)
        sbuf = np.zeros(Ls)
        state, ext, entry, first = 0.0, 0.0, 0.0, True
        s = rng_state[i]
        wa = 0
        ws = 0
        for k in range(steps):
            y = Sr[i, 0] * p[0] + Sr[i, 1] * p[1]
            if noise[i] > 0:
                s = _lcg(s)
                y += noise[i] * table[(s >> 40) & mask]
            state, ext, entry, first = _relay(-y, beta[i], band[i], state, ext, entry, first)
            ref = bias[i] + h[i] * state
            if k >= start:
                U[i, k - start] = ref
                Y[i, k - start] = y
            theta = Kr[i, 0] * z[0] + Kr[i, 1] * z[1] + Kr[i, 2] * z[2]
            rate = Krl[i, 0] * z[0] + Krl[i, 1] * z[1] + Krl[i, 2] * z[2]
            u_att = Kc[i] * (ref - theta) - Kd[i] * rate
            # side part driven by the attitude
            sbuf[ws] = theta
            r0 = ws - sd_[i]
            if r0 < 0:
                r0 += Ls
            r1 = r0 - 1
            if r1 < 0:
                r1 += Ls
            for j in range(2):
                p[j] = Sd[i, j] * p[j] + S0[i, j] * sbuf[r0] + S1[i, j] * sbuf[r1]
            ws += 1
            if ws == Ls:
                ws = 0
            # attitude plant driven by the PD
            abuf[wa] = u_att
            r0 = wa - d[i]
            if r0 < 0:
                r0 += La
            r1 = r0 - 1
            if r1 < 0:
                r1 += La
            for j in range(3):
                z[j] = Ad[i, j] * z[j] + B0[i, j] * abuf[r0] + B1[i, j] * abuf[r1]
            wa += 1
            if wa == La:
                wa = 0
        rng_state[i] = s
