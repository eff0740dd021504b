"""The identification worker: a real child process, pickles over its standard pipes."""

from __future__ import annotations

import pytest

from mrft_gcs.errors import IdentificationError
from mrft_gcs.flight.sequence import CycleSnapshot
from mrft_gcs.identify import CycleStatus, relay_settings
from mrft_gcs.identify.live import bundled_identifier, synthetic_cycles
from mrft_gcs.identify.worker import AVAILABLE, IdentificationWorker, WorkerError
from mrft_gcs.loops import Loop, LoopKind

pytestmark = pytest.mark.skipif(not AVAILABLE, reason="the worker needs a POSIX system")


def _roll_snapshot() -> CycleSnapshot:
    t, u, y = synthetic_cycles(0.3, 0.12, 0.05)
    beta = relay_settings(LoopKind.ATTITUDE).beta
    return CycleSnapshot(Loop.ROLL, t, u, y, beta, 0.12, 0.0, CycleStatus(6, True, 0.3, 0.05, 0))


def _off_setpoint_altitude() -> CycleSnapshot:
    """Altitude cycles 4.7 m from their set point: refused (they never cross it)."""
    t, u, y = synthetic_cycles(0.75, 0.1, 0.04)
    beta = relay_settings(LoopKind.ALTITUDE).beta
    return CycleSnapshot(Loop.ALTITUDE, t, u + 0.5, y + 0.3, beta, 0.1, 0.5,
                         CycleStatus(6, True, 0.75, 0.04, 0), setpoint=5.0)


@pytest.fixture(scope="module")
def worker():
    with IdentificationWorker() as w:
        att, alt = relay_settings(LoopKind.ATTITUDE), relay_settings(LoopKind.ALTITUDE)
        w.call("warm", att, alt, timeout_s=120.0)
        yield w


def test_the_worker_identifies_as_this_process_does(worker):
    snap = _roll_snapshot()
    here = bundled_identifier(Loop.ROLL, snap)
    there = worker.call("identify", Loop.ROLL, snap, None)
    assert there.class_index == here.class_index
    assert there.gains == here.gains  # same code, same numbers: bit for bit
    assert there.model.as_dict() == here.model.as_dict()


def test_a_refused_identification_is_raised_again_in_the_caller(worker):
    snap = _off_setpoint_altitude()
    with pytest.raises(IdentificationError) as here:
        bundled_identifier(Loop.ALTITUDE, snap)
    with pytest.raises(IdentificationError) as there:
        worker.call("identify", Loop.ALTITUDE, snap, None)
    assert str(there.value) == str(here.value)
    # and the worker goes on serving
    assert worker.call("identify", Loop.ROLL, _roll_snapshot(), None).gains is not None


def test_the_attitude_paths_closed_loop_is_measured_there_too(worker):
    """``attitude_loop`` (:func:`mrft_gcs.identify.live.measured_attitude_loop`): a side
    snapshot without a tilt record is refused there as here."""
    from mrft_gcs.identify.live import measured_attitude_loop

    snap = _roll_snapshot()  # no tilt record
    with pytest.raises(IdentificationError, match="no measured tilt") as here:
        measured_attitude_loop(snap)
    with pytest.raises(IdentificationError) as there:
        worker.call("attitude_loop", snap)
    assert str(there.value) == str(here.value)


def test_a_worker_that_died_is_a_worker_error_not_a_hang():
    w = IdentificationWorker()
    w._proc.kill()
    w._proc.wait()
    with pytest.raises(WorkerError, match=r"exited \(code -9\)"):
        w.call("identify", Loop.ROLL, _roll_snapshot(), None, timeout_s=5.0)
    w.close()
    w.close()  # twice is harmless


def test_a_worker_that_does_not_answer_times_out():
    import signal

    w = IdentificationWorker()
    try:
        w._proc.send_signal(signal.SIGSTOP)  # alive, but never answers
        with pytest.raises(WorkerError, match="did not answer within 0.5 s"):
            w.call("identify", Loop.ROLL, _roll_snapshot(), None, timeout_s=0.5)
    finally:
        w._proc.send_signal(signal.SIGCONT)
        w.close()
