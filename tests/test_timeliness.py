"""The ground station's loop timeliness: the rules, a stalled lockstep tune, a stalled SITL."""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
sys.path.insert(0, str(Path(__file__).parent))

import tune_population as tp  # noqa: E402
from flight_sim import ALT_RELAY, ATT_RELAY, SIDE_RELAY, truth_identifier  # noqa: E402

from mrft_gcs.flight import safety  # noqa: E402
from mrft_gcs.flight.controllers import FlightState  # noqa: E402
from mrft_gcs.flight.safety import RelayTooLarge, SafetyMonitor  # noqa: E402
from mrft_gcs.flight.timeliness import HostTooSlow, TimelinessMonitor  # noqa: E402
from mrft_gcs.loops import LoopKind  # noqa: E402
from mrft_gcs.profiles import SafetyLimits  # noqa: E402
from mrft_gcs.sitl import SitlProcess, domain_check, random_airframe  # noqa: E402


def _steady(m: TimelinessMonitor, t0: float, t1: float, dt: float = 0.004) -> float:
    """Samples and ticks every ``dt`` from ``t0`` to ``t1``; returns the last time."""
    t = t0
    while t <= t1 + 1e-9:
        m.sample(t)
        m.tick(t)
        t += dt
    return t - dt


def test_a_steady_loop_with_short_gaps_is_no_trouble():
    m = TimelinessMonitor()
    t = _steady(m, 0.0, 2.0)
    t = _steady(m, t + 0.045, t + 1.0)  # one 45 ms gap, as a quiet machine shows
    assert m.trouble(t) is None and m.summary() is None


def test_one_long_stall_is_trouble_at_once_and_named():
    m = TimelinessMonitor()
    t = _steady(m, 0.0, 1.0)
    m.sample(t + 0.124)
    why = m.trouble(t + 0.124)
    assert why == "telemetry stopped for 124 ms (the rule: none of 100 ms or more)"


def test_a_gap_still_going_on_is_trouble():
    m = TimelinessMonitor()
    t = _steady(m, 0.0, 1.0)
    assert m.trouble(t + 0.09) is None
    assert "telemetry stopped 110 ms ago" in m.trouble(t + 0.11)


def test_two_short_stalls_stop_relays_three_the_hover_and_old_ones_expire():
    m = TimelinessMonitor()
    t = _steady(m, 0.0, 1.0)
    t = _steady(m, t + 0.06, t + 1.0)
    assert m.trouble(t) is None  # one 60 ms stall
    t = _steady(m, t + 0.07, t + 0.5)
    assert "2 stalls of 50 ms or more within 3 s" in m.trouble(t)
    assert m.trouble(t, relays=False) is None  # the hover's PDs take two
    t = _steady(m, t + 0.08, t + 0.2)
    assert "3 stalls" in m.trouble(t, relays=False)
    t = _steady(m, t, t + 3.5)  # quiet for longer than the window
    assert m.trouble(t) is None
    assert "3 stalls of 50 ms or more" in m.summary() and "80 ms" in m.summary()


def test_a_stall_seen_by_the_reader_and_the_stream_counts_once():
    m = TimelinessMonitor()
    t = _steady(m, 0.0, 1.0)
    m.sample(t + 0.07)  # a starved process: telemetry and set points stop together
    m.tick(t + 0.072)
    t = _steady(m, t + 0.072, t + 1.0)
    assert m.trouble(t) is None and len(m.stalls) == 1
    assert m.stalls[0].length_s == pytest.approx(0.072)


def test_a_gap_counts_as_long_as_the_vehicle_flew_through_it():
    """A vehicle that flew on through a 120 ms gap sends that flight in a burst at its end (a
    held set point): a stall. One whose clock stood still (a simulator stopped whole) goes on
    from where it stopped: no stall, however long the gap."""
    m = TimelinessMonitor()
    rx = vt = 0.0
    for _ in range(250):
        rx += 0.004
        vt += 0.004
        m.sample(rx, vt)
    rx += 0.3  # stood still for 0.3 s: the vehicle's clock slips
    for _ in range(20):
        vt += 0.004
        m.sample(rx, vt)
        rx += 0.004
    assert m.trouble(rx) is None and m.stalls == []
    rx += 0.12  # flew on for 0.12 s: all of it arrives at once
    for _ in range(30):
        vt += 0.004
        m.sample(rx, vt)
    assert m.trouble(rx) is None  # still reading what follows the gap
    for _ in range(10):
        rx += 0.004
        vt += 0.004
        m.sample(rx, vt)
    assert m.trouble() == "telemetry stopped for 124 ms (the rule: none of 100 ms or more)"


def test_the_relay_guard_stops_short_of_the_tilt_limit():
    mon = SafetyMonitor(SafetyLimits(max_tilt_deg=35.0), (0.0, 0.0, 0.0), 0.0)

    def at(deg: float) -> FlightState:
        r = math.radians(deg)
        return FlightState(1.0, r, 0, 0, 0, 0, 0, 1.0, 0, 0, 1.0, 0, 0, 0)

    mon.relay_guard(at(31.0), "inner MRFT relay test")
    with pytest.raises(RelayTooLarge, match="past 90% of the 35 deg limit") as err:
        mon.relay_guard(at(32.0), "inner MRFT relay test")
    assert err.value.exit_code == 6 and mon.violation(at(32.0)) is None


STALLED_SEED = 31  # a light in-domain vehicle (66 g) whose relays a stalled loop tips over


def test_a_stalled_lockstep_tune_stops_early_where_it_ran_past_the_limit(monkeypatch):
    """Ground-station stalls of 48-96 ms about every half second (the vehicle keeps the last
    set point meanwhile): without the timeliness check (and the relay guard) the take-off's
    relays run past the tilt limit; with it the tune stops on the second stall, well short."""
    assert domain_check(random_airframe(STALLED_SEED)).category == "in-domain"
    with monkeypatch.context() as mp:
        mp.setattr(safety, "RELAY_GUARD_FRACTION", 10.0)
        before = tp.run_lockstep(STALLED_SEED, stalls=(96.0, 0.5), timeliness=False)
    assert before["outcome"] == "aborted" and "tilt" in before["reason"]
    assert before["max_tilt_deg"] > 35.0
    after = tp.run_lockstep(STALLED_SEED, stalls=(96.0, 0.5))
    assert after["outcome"] == "refused", after["reason"]
    assert "could not keep the" in after["reason"] and "2 stalls" in after["reason"]
    assert after["max_tilt_deg"] < 0.7 * 35.0
    quiet = tp.run_lockstep(STALLED_SEED)  # the same vehicle on time: no false alarm
    assert quiet["outcome"] == "completed", quiet["reason"]


RELAY = {LoopKind.ATTITUDE: ATT_RELAY, LoopKind.ALTITUDE: ALT_RELAY, LoopKind.SIDE: SIDE_RELAY}


@pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="needs SIGSTOP (POSIX)")
def test_a_vehicle_process_stalled_mid_test_stops_the_tune_and_lands(tmp_path):
    """The SITL process is stopped for 0.2 s while the relays run (SIGSTOP, SIGCONT): its
    telemetry stops, and it catches up on the held set point. The tool stops the tests with
    a one-line reason (exit code 3) and commands the landing; nothing is written."""
    from mrft_gcs.flight import tune
    from mrft_gcs.link import VehicleLink

    ti = truth_identifier("qdrone")
    with SitlProcess(vehicle="qdrone", port=None, seed=8) as sitl:
        pid = sitl.pid
        assert pid is not None

        def stall() -> None:
            os.kill(pid, signal.SIGSTOP)
            time.sleep(0.2)
            os.kill(pid, signal.SIGCONT)

        staller = threading.Thread(target=stall, daemon=True)

        def progress(snap: dict) -> None:
            if snap["stream_sent"] > 500 and staller.ident is None:  # two seconds in the air
                staller.start()

        try:
            with pytest.raises(HostTooSlow) as err:
                tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                     identifier=lambda lp, snap, inner: ti(lp, snap, inner),
                     on_progress=progress)
        finally:
            if staller.ident is not None:
                staller.join(2.0)
        with VehicleLink.connect(sitl.connection_string) as link:  # told to land
            deadline = time.monotonic() + 2.0
            while (link.heartbeat.custom_mode >> 16) & 0xFF != 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert (link.heartbeat.custom_mode >> 16) & 0xFF == 4  # AUTO (LAND)
    msg = str(err.value)
    assert err.value.exit_code == 3 and "\n" not in msg
    assert "stopped for" in msg and "landing commanded" in msg
    partial = err.value.partial_result
    assert partial.parameters == () and partial.max_tilt_deg < 35.0


def test_the_relay_guard_stops_a_live_relay_short_of_the_limit_and_lands(tmp_path):
    """A tilt limit of 3 deg, below what the attitude relays swing: the guard stops the test
    at 90 % of it, before the limit, with exit code 6, and the vehicle is told to land."""
    from mrft_gcs.flight import tune
    from mrft_gcs.link import VehicleLink
    from mrft_gcs.profiles import load_profile

    ti = truth_identifier("qdrone")
    limits = load_profile("sitl").safety.with_overrides(max_tilt_deg=3.0)
    with SitlProcess(vehicle="qdrone", port=None, seed=5) as sitl:
        with pytest.raises(RelayTooLarge, match="past 90% of the 3 deg limit") as err:
            tune(sitl.connection_string, "sitl", backup_dir=tmp_path, relay=RELAY,
                 identifier=lambda lp, snap, inner: ti(lp, snap, inner), limits=limits)
        with VehicleLink.connect(sitl.connection_string) as link:
            deadline = time.monotonic() + 2.0
            while (link.heartbeat.custom_mode >> 16) & 0xFF != 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert (link.heartbeat.custom_mode >> 16) & 0xFF == 4  # AUTO (LAND)
    assert err.value.exit_code == 6
    partial = err.value.partial_result
    assert partial.parameters == () and partial.max_tilt_deg < 3.0
