"""The vehicle-clock model (mrft_gcs.link.clock) on synthetic timestamp streams."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.link.clock import ClockModel, clock_bins, fit_clock


def stream(seed: int, *, ppm: float = 0.0, slips: tuple[tuple[float, float], ...] = (),
           duration_s: float = 40.0, rate_hz: float = 250.0, jitter_s: float = 0.0003,
           late: tuple[float, float, float] | None = None):
    """ATTITUDE-like samples: vehicle times, receive times and the true clock offset.

    The vehicle's clock runs ``ppm`` slow against the receiver's and stops for ``step`` s
    of real time at each ``(vehicle time, step)`` of ``slips``; the link adds 0.2 ms plus
    exponential jitter; ``late`` = (start, end, extra): every sample received in that span
    of vehicle time is late by ``extra`` (the ground station's reader starved).
    """
    rng = np.random.default_rng(seed)
    vt = np.round(np.arange(0.0, duration_s, 1.0 / rate_hz) * 1e3) / 1e3  # time_boot_ms
    off = 1000.0 + vt * ppm * 1e-6
    for t, step in slips:
        off = off + step * (vt >= t)
    lat = 0.0002 + rng.exponential(jitter_s, len(vt))
    if late is not None:
        lat = lat + late[2] * ((vt >= late[0]) & (vt < late[1]))
    rx = vt + off + lat
    return vt, rx, off + 0.0002


@pytest.mark.parametrize("ppm", [0.0, 200.0, -200.0])
@pytest.mark.parametrize("slips", [(), ((13.3, 0.005),), ((9.1, 0.012), (25.7, 0.020))])
def test_envelope_tracks_drift_and_slips(ppm, slips):
    vt, rx, true = stream(int(ppm) + 300 + 7 * len(slips), ppm=ppm, slips=slips)
    fit = fit_clock(clock_bins(rx, vt))
    assert fit.skew_ppm == pytest.approx(ppm, abs=40.0)
    assert [round(s.step_s, 3) for s in fit.slips] == pytest.approx(
        [s for _, s in slips], abs=1.5e-3)
    for (t, _), sl in zip(slips, fit.slips, strict=True):
        assert sl.t0_s <= t <= sl.t1_s + 1e-9
    # away from the slips (a bin either side), the envelope is the least-delayed offset
    # within a fraction of the jitter; a constant offset taken once misses by the slips
    far = np.all([np.abs(vt - t) > 1.0 for t, _ in slips], axis=0) if slips else vt >= 0
    err = fit.offset_at(vt[far]) - true[far]
    assert np.max(np.abs(err)) < 3e-4, np.max(np.abs(err))
    once = np.min(rx - vt)
    if slips:
        assert np.max(true - once) > max(s for _, s in slips) - 5e-4


def test_a_starved_reader_is_no_slip():
    # every sample late by 8 ms for 0.4 s (under a bin): the envelope ignores it
    vt, rx, true = stream(3, late=(17.1, 17.5, 0.008))
    fit = fit_clock(clock_bins(rx, vt))
    assert fit.slips == ()
    assert np.max(np.abs(fit.offset_at(vt) - true)) < 3e-4


def test_streaming_equals_offline_and_inverts():
    vt, rx, _ = stream(5, ppm=150.0, slips=((20.2, 0.009),))
    # two interleaved streams (ATTITUDE, LOCAL_POSITION_NED) received in order
    vt2, rx2, _ = stream(6, ppm=150.0, slips=((20.2, 0.009),), rate_hz=50.0)
    order = np.argsort(np.concatenate([rx, rx2]), kind="stable")
    v, r = np.concatenate([vt, vt2])[order], np.concatenate([rx, rx2])[order]
    live = ClockModel()
    for a, b in zip(r.tolist(), v.tolist(), strict=True):
        live.update(a, b)
    on, off = live.bins(), clock_bins(r, v)
    for f in ("key", "vt_s", "offset_s", "count"):
        np.testing.assert_array_equal(getattr(on, f), getattr(off, f))
    fit = live.fit()
    assert fit.resolution_s == 1e-3
    assert len(fit.slips) == 1
    # to_vehicle inverts vt + offset_at(vt) away from the slip
    q = vt[(vt > 1) & (np.abs(vt - 20.2) > 1.0)]
    np.testing.assert_allclose(fit.to_vehicle(q + fit.offset_at(q)), q, atol=1e-9)


def test_reboot_resets_and_empty_fit():
    c = ClockModel()
    assert np.isnan(c.offset_s) and c.fit().empty
    assert np.isnan(c.fit().offset_at([1.0])[0])
    for i in range(600):
        c.update(10.0 + i * 0.004, i * 0.004)
    c.update(30.0, 0.1)  # vehicle time went back: a new boot
    assert c.bins().count.tolist() == [1]
