"""dry-run: relay tests found in logs, explained when absent; CLI; identification wiring."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mrft_gcs.cli import main
from mrft_gcs.dryrun import dry_run, find_relay_segments, infer_beta
from mrft_gcs.loops import Loop
from mrft_gcs.plant import InnerModel
from mrft_gcs.residual.synth import sitl_relay_record, write_relay_tlog
from mrft_gcs.telemetry import TelemetryLog

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "logs"
REAL = [SHARED / "px4-sample-flight.ulg", SHARED / "ardupilot-sample.bin"]
MODELS = ROOT / "models" / "manifest.json"


@pytest.fixture(scope="module")
def relay_tlog(tmp_path_factory):
    rec = sitl_relay_record("roll", effects={"sensor_lpf": 15.0}, seed=3, beta=-0.5, h=0.08,
                            duration_s=6.0)
    path = tmp_path_factory.mktemp("dry") / "relay.tlog"
    write_relay_tlog(path, "roll", rec.t, rec.u, rec.y)
    return path, rec


@pytest.mark.parametrize("path", REAL, ids=lambda p: p.name)
def test_real_logs_explain_that_no_relay_test_is_there(path):
    if not path.exists():
        pytest.skip(f"{path} not found")
    res = dry_run(path)
    assert not res.found
    text = res.explanation()
    assert "no relay test found" in text
    for loop in ("roll", "pitch", "altitude", "x", "y"):
        assert f"  {loop}: " in text
    assert "signals in the log" in text


@pytest.mark.parametrize("path", REAL, ids=lambda p: p.name)
def test_cli_on_real_logs_exits_cleanly(path, tmp_path, capsys):
    if not path.exists():
        pytest.skip(f"{path} not found")
    report = tmp_path / "r.json"
    assert main(["dry-run", str(path), "--report", str(report)]) == 6  # nothing identified
    assert "no relay test found" in capsys.readouterr().out
    data = json.loads(report.read_text())
    assert data["loops"] == {} and data["status"] == "no_identification"


def test_relay_found_in_tlog_with_its_settings(relay_tlog):
    path, rec = relay_tlog
    res = dry_run(path, models={Loop.ROLL: rec.model})
    assert [r.loop for r in res.loops] == [Loop.ROLL]
    r = res.loops[0]
    assert r.segment.source == "actuator"
    assert r.segment.h == pytest.approx(0.08, rel=1e-3)
    assert r.segment.beta == pytest.approx(-0.5, abs=0.05)
    # Without bundled classifiers the known model is used for the residual.
    assert r.residual is not None and r.residual.effect == "sensor_lpf"
    assert "pitch" in res.searched and "constant" in res.searched["pitch"]


def test_metadata_beta_wins_and_csv_loops_are_read(tmp_path):
    rec = sitl_relay_record("roll", seed=2, beta=-0.3, h=0.06, duration_s=4.0)
    path = tmp_path / "relay.csv"
    rows = "\n".join(f"{t:.4f},roll,{u:.5f},{y:.6f}"
                     for t, u, y in zip(rec.t, rec.u, rec.y, strict=True))
    path.write_text(f"# mrft-gcs loop csv v1\n# beta=-0.3 h=0.06\nt,loop,u,y\n{rows}\n")
    res = dry_run(path, models={Loop.ROLL: rec.model})
    seg = res.loops[0].segment
    assert seg.source == "csv" and seg.beta_from == "metadata" and seg.beta == -0.3
    assert infer_beta(rec.u, rec.y) == pytest.approx(-0.3, abs=0.06)


def test_controller_output_is_not_a_relay():
    t = np.arange(0, 20, 0.004)
    rng = np.random.default_rng(0)
    att = np.column_stack([t, 0.05 * np.sin(3 * t), *(0 * t for _ in range(5))])
    act = np.column_stack([t, 0.1 * np.cos(3 * t) + 0.01 * rng.standard_normal(t.size),
                           0 * t, 0 * t, 0.5 + 0 * t])
    segs, why = find_relay_segments(TelemetryLog(attitude=att, actuator=act))
    assert segs == [] and "not a two-level relay" in why["roll"]


def test_identify_wiring_once_models_exist(tmp_path):
    if not MODELS.exists() or not list((MODELS.parent / "attitude").glob("*.onnx")):
        pytest.skip("the attitude classifier is not bundled yet (models/)")
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.loops import LoopKind

    beta = relay_settings(LoopKind.ATTITUDE).beta
    rec = sitl_relay_record("roll", seed=4, beta=beta, h=0.08, duration_s=6.0)
    path = tmp_path / "tune.tlog"
    write_relay_tlog(path, "roll", rec.t, rec.u, rec.y)
    r = dry_run(path).loops[0]
    assert r.segment.beta == beta and r.segment.beta_from == "domain"
    assert r.identification is not None, r.notes
    assert isinstance(r.identification.model, InnerModel)
    assert r.identification.gains.Kc > 0 and r.identification.gains.Kd > 0
    assert r.residual is not None


def test_steady_verdicts_equal_the_live_detector_fed_sample_by_sample():
    """``_steady_rises`` (whole arrays) says "steady" at exactly the rising switches where a
    :class:`CycleDetector` fed one sample at a time, as the live sequence feeds it (period
    tolerance widened to 2.5 sample intervals for short cycles), says so."""
    import math

    from mrft_gcs.dryrun import _steady_rises
    from mrft_gcs.identify import CycleDetector

    for loop, n, seed, relax in (("roll", 3, 1, None), ("roll", 3, 4, None),
                                 ("altitude", 2, 2, None), ("roll", 3, 4, 8)):
        rec = sitl_relay_record(loop, seed=seed, beta=-0.7 if loop == "roll" else -0.3, h=0.1,
                                duration_s=8.0 if loop == "roll" else 20.0)
        # irregular sampling, as telemetry arrives
        t = rec.t + np.random.default_rng(seed).uniform(0, 0.002, rec.t.size).cumsum()
        if relax is not None:  # cycles that miss the strict tolerances now and then
            rec.y[:] += 0.06 * np.abs(rec.y).max() * np.sin(2 * np.pi * 0.7 * t)
        det, status, dt_avg, live = CycleDetector(n_periods=n, relax_after=relax), None, \
            math.nan, {}
        for k, (ti, ui, yi) in enumerate(zip(t, rec.u, rec.y, strict=True)):
            if det.t and status is not None and math.isfinite(status.period_s):
                dt = ti - det.t[-1]
                dt_avg = dt if not math.isfinite(dt_avg) else 0.99 * dt_avg + 0.01 * dt
                det.period_tol = max(0.03, 2.5 * dt_avg / status.period_s)
            before = len(det.rise_t)
            status = det.update(ti, ui, yi)
            if len(det.rise_t) != before:
                live[k] = status.steady
        rises, steady = _steady_rises(t, rec.u, rec.y, n, 0.03, 0.08, relax)
        assert list(rises) == list(live)
        assert [bool(s) for s in steady] == list(live.values())
        assert any(steady) and not all(steady)
        if relax is not None:  # the relaxed tolerances did decide some verdicts
            assert (steady != _steady_rises(t, rec.u, rec.y, n, 0.03)[1]).any()


@pytest.mark.parametrize("lateness", [(0, 0, 0, 1, 2, 3), (0, 1, 1, 1, 2)])
def test_commands_are_paired_with_the_sample_they_answered(lateness):
    """A simulated ground station answers attitude samples 4 ms apart; on a loaded machine
    a sample often reaches the log while a command is being computed, so the command is
    logged after a sample it never saw (here one in two, up to three samples late; or, as
    the phase between telemetry and stream can fall, most commands one sample late: a CI
    tune logged 47 % on the latest sample and 52 % on the one before, and the pairing
    had given up). The yaw hold's torque on every command tells which sample it
    answered: the pairing gives the samples the relay saw and the relay output it gave
    each, where file order alone would not."""
    from mrft_gcs.dryrun import _answer_order, _pair
    from mrft_gcs.flight.controllers import YawHold

    rng = np.random.default_rng(7)
    n = 2000
    t = 5.0 + 0.004 * np.arange(n)
    yaw = 0.3 + 1e-3 * rng.standard_normal(n)
    r = 0.01 * rng.standard_normal(n)
    att = np.column_stack([t, 0.05 * np.sin(20 * t), 0 * t, yaw, 0 * t, 0 * t, r])
    relay = np.where(np.sin(20 * t) > 0, -0.12, 0.12)  # the output each sample gets
    hold = YawHold()
    rows, order_cmd, answered = [], [], []
    k = 0
    while k < n - 4:
        late = int(rng.choice(lateness))
        logged_after = min(k + late, n - 1)  # the newest sample logged before the command
        tau = hold.step(0.3, yaw[k], r[k])
        rows.append((t[logged_after] + 0.001, relay[k], 0.0, tau, 0.5))
        order_cmd.append(2 * logged_after + 1)  # file position: after that sample
        answered.append(k)
        k += int(rng.choice([1, 1, 1, 2]))  # now and then a sample no command answers
    act = np.array(rows)
    log = TelemetryLog(attitude=att, actuator=act)
    order = {"attitude": 2 * np.arange(n), "actuator": np.array(order_cmd)}
    fixed = _answer_order(log, order)
    assert float(fixed["yaw_ref"][0]) == pytest.approx(0.3, abs=1e-9)
    c = _pair(att, fixed["attitude"], act[:, 0], fixed["actuator"])
    first = {}
    for j, a in enumerate(answered):
        first.setdefault(a, j)
    assert list(c.rows) == sorted(first)
    np.testing.assert_array_equal(act[c.cmd, 1], relay[c.rows])
    naive = _pair(att, 2 * order["attitude"], act[:, 0], 2 * order["actuator"])
    assert list(naive.rows) != sorted(first)


def test_dry_run_designs_on_the_rate_target_filter_the_log_holds(tmp_path):
    """An ArduPilot's rate-target low-pass (``ATC_RAT_RLL_FLTT``) logged before the relay
    test shapes the written roll gains as a live tune shapes them; without it the same
    test gives the plain PD."""
    from mrft_gcs.dryrun import log_structure
    from mrft_gcs.flight.scoring import general_ise
    from mrft_gcs.flight.structure import structure_controller
    from mrft_gcs.logs import decode_log
    from mrft_gcs.pd_design import frequency_grid, margins
    from mrft_gcs.plant import inner_response

    rec = sitl_relay_record("roll", seed=3, beta=-0.7, h=0.08, duration_s=6.0)
    plain, filt = tmp_path / "plain.tlog", tmp_path / "fltt.tlog"
    write_relay_tlog(plain, "roll", rec.t, rec.u, rec.y)
    write_relay_tlog(filt, "roll", rec.t, rec.u, rec.y, params={"ATC_RAT_RLL_FLTT": 8.0})
    st = log_structure(decode_log(filt))
    assert st[Loop.ROLL].target_hz == 8.0 and "read" in st[Loop.ROLL].source
    assert st[Loop.PITCH].target_hz == 20.0  # ArduPilot's default: the log does not say
    assert log_structure(decode_log(plain))[Loop.ROLL].plain
    a, b = (dry_run(p, loops=(Loop.ROLL,)).loops[0] for p in (plain, filt))
    assert a.identification is not None and b.identification is not None
    assert a.identification.gains == b.identification.gains  # the same test, identified
    assert "rate target low-pass 8 Hz" in " ".join(b.notes)
    assert "rate target" not in " ".join(a.notes)
    # on the loop the autopilot closes (filter in, the re-targeted delay), the gains
    # designed for it follow a step better than the plain PD, and keep their margin
    m = a.identification.model
    w = frequency_grid(m.T_prop, m.T1, m.tau)
    G = inner_response(m.K, m.T_prop, m.T1, m.tau - b.gcs_delay_s, w)[0]
    fig = {}
    for k, r in (("plain", a), ("designed", b)):
        Cr, Cy = structure_controller(r.gains, st[Loop.ROLL], w)
        fig[k] = (general_ise(Cr, Cy, G, w), margins(Cy * G, w).pm_deg)
    assert fig["designed"][0] < 0.97 * fig["plain"][0] and fig["designed"][1] >= 15.0, fig


def test_dry_run_clamps_parameters_into_the_profile_range(tmp_path):
    """A profile whose range the tuned roll angle P exceeds: clamped, with the loop's note."""
    if not MODELS.exists() or not list((MODELS.parent / "attitude").glob("*.onnx")):
        pytest.skip("the attitude classifier is not bundled yet (models/)")
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.profiles import PROFILE_DIR

    rec = sitl_relay_record("roll", seed=4, beta=relay_settings(LoopKind.ATTITUDE).beta,
                            h=0.08, duration_s=6.0)
    log = tmp_path / "tune.tlog"
    write_relay_tlog(log, "roll", rec.t, rec.u, rec.y)
    text = (PROFILE_DIR / "sitl.toml").read_text()
    assert "MC_ROLL_P = [0.0, 50.0]" in text
    tight = tmp_path / "tight.toml"
    tight.write_text(text.replace("MC_ROLL_P = [0.0, 50.0]", "MC_ROLL_P = [0.0, 0.5]"))
    report = tmp_path / "r.json"
    assert main(["dry-run", str(log), "--profile", str(tight), "--report", str(report)]) == 0
    data = json.loads(report.read_text())
    params = {p["name"]: p["new"] for p in data["parameters"]}
    gains = data["loops"]["roll"]["gains"]
    assert gains["Kc"] / gains["Kd"] > 0.5  # the tuned angle P is above the range ...
    assert params["MC_ROLL_P"] == 0.5  # ... so its upper bound is written
    assert params["MC_ROLLRATE_P"] == pytest.approx(gains["Kd"])  # inside: as computed
    notes = [n for n in data["loops"]["roll"]["notes"] if n.startswith("MC_ROLL_P:")]
    assert len(notes) == 1
    assert f"the tuned {gains['Kc'] / gains['Kd']:.4g} is above the profile's range 0 to 0.5; " \
           f"0.5 written (roll angle loop slower than designed; in effect Kc " in notes[0]
    assert notes[0] in data["explanation"]


def _independent_relay_logs(folder: Path, n: int = 30, seed: int = 22):
    """``n`` MRFT logs in the documented CSV format, no beta in their metadata: attitude
    plants drawn log-uniformly over the attitude domain (gains 5-60), relay beta -0.7 with
    a bias of 0.2-0.26 h (either sign), a set point off zero, measurement noise (0.5-2 %
    of the amplitude) on the logged angle, 250 Hz. Draws whose relay lost its set point
    (the cycle no longer crosses it every half cycle, then the relay's guard drives it: no
    MRFT test) are replaced by the next draw. Returns ``[(path, truth)]``."""
    from mrft_gcs.domains import D_ATT
    from mrft_gcs.simulate import simulate_mrft

    rng = np.random.default_rng(seed)
    m = 2 * n
    p = D_ATT.sample_log_uniform(m, rng)
    K = np.exp(rng.uniform(np.log(5.0), np.log(60.0), m))
    h = rng.uniform(0.03, 0.1, m)
    bias = rng.uniform(0.2, 0.26, m) * h * rng.choice([-1.0, 1.0], m)
    run = simulate_mrft(K, p[:, 0], p[:, 1], p[:, 2], -0.7, h, bias=bias, duration_s=20.0,
                        dt=0.004)
    out = []
    for i in range(m):
        u, y = run.u[i], run.y[i]
        high = u > bias[i]
        sw = np.flatnonzero(high[1:] != high[:-1]) + 1
        sw = sw[sw > u.size // 2]
        if not all((y[a:b].min() < 0) if high[a] else (y[a:b].max() > 0)
                   for a, b in zip(sw[:-1], sw[1:], strict=False)):
            continue
        amp = 0.5 * float(np.ptp(y[u.size // 2:]))
        r0 = float(rng.uniform(-0.05, 0.05))
        y = y + r0 + rng.uniform(0.005, 0.02) * amp * rng.standard_normal(u.size)
        path = folder / f"relay{i:02d}.csv"
        rows = "\n".join(f"{a:.4f},roll,{b:.5f},{c:.6f}"
                         for a, b, c in zip(run.t, u, y, strict=True))
        path.write_text(f"# mrft-gcs loop csv v1\nt,loop,u,y\n{rows}\n")
        out.append((path, {"setpoint": r0, "amplitude": amp, "h": float(h[i]),
                           "bias": float(bias[i]),
                           "params": tuple(map(float, p[i]))}))
        if len(out) == n:
            return out
    raise AssertionError("too few draws kept their set point")


def test_beta_and_set_point_of_biased_relays_without_metadata(tmp_path):
    """30 independent-looking MRFT logs with a biased relay (0.2-0.26 h) and no beta in
    their metadata: every one gives beta -0.7 and its set point from the switches, and
    dry-run identifies every one (an estimate from the error extremes of one state, biased
    cycles off-centre, had given beta -0.91 and a refusal on some)."""
    from mrft_gcs.dryrun import infer_relay

    logs = _independent_relay_logs(tmp_path)
    have_models = MODELS.exists() and list((MODELS.parent / "attitude").glob("*.onnx"))
    refused = []
    for path, truth in logs:
        data = np.genfromtxt(path, delimiter=",", skip_header=2, usecols=(0, 2, 3))
        inf = infer_relay(data[:, 1], data[:, 2])
        assert inf.beta == pytest.approx(-0.7, abs=0.03), (path.name, truth)
        assert inf.setpoint == pytest.approx(truth["setpoint"], abs=0.05 * truth["amplitude"])
        assert inf.crossed > 0.95  # the first half cycle may still be settling
        if not have_models:
            continue
        r = dry_run(path).loops[0]
        assert r.segment.beta == -0.7 and r.segment.beta_from == "domain"
        assert r.segment.h == pytest.approx(truth["h"], rel=1e-3)
        if r.identification is None:
            refused.append((path.name, r.notes))
    assert refused == []


def test_a_relay_that_lost_its_set_point_is_explained(tmp_path):
    """Noise in the loop fired the first switch before the plant moved; the lead relay
    (beta -0.7) switches before the angle comes back, so the cycle drifts off the set
    point and the relay's guard drives it: no MRFT test. dry-run says so instead of
    naming some beta."""
    from mrft_gcs.simulate import simulate_mrft

    run = simulate_mrft(8.3, 0.072, 0.8, 0.0034, -0.7, 0.06, noise_std=5e-4, band=2e-3,
                        duration_s=12.0, dt=0.004, seed=0, engine="numpy")
    path = tmp_path / "drift.csv"
    rows = "\n".join(f"{a:.4f},roll,{b:.5f},{c:.6f}"
                     for a, b, c in zip(run.t, run.u[0], run.y[0], strict=True))
    path.write_text(f"# mrft-gcs loop csv v1\nt,loop,u,y\n{rows}\n")
    r = dry_run(path).loops[0]
    assert r.segment.crossed < 0.9 and r.segment.beta_from == "switches"
    assert r.identification is None
    assert "lost its set point" in r.notes[0] and "--beta" in r.notes[0]


def test_dry_run_designs_roll_and_pitch_on_their_pooled_lags_as_a_tune_does(tmp_path):
    """Roll and pitch of one vehicle: the would-be gains are designed on the models with
    their fast lags pooled (a tune's write, :func:`mrft_gcs.flight.onboard.pooled_attitude`),
    the identified models stay as identified, and the note says so."""
    import math

    from mrft_gcs.dryrun import _gcs_delay, _pool_roll_pitch
    from mrft_gcs.flight.onboard import pooled_attitude, robust_onboard_gains

    res = {}
    for axis in ("roll", "pitch"):
        rec = sitl_relay_record(axis, seed=5, beta=-0.7, h=0.08, duration_s=6.0)
        write_relay_tlog(tmp_path / f"{axis}.tlog", axis, rec.t, rec.u, rec.y)
        res[Loop(axis)] = dry_run(tmp_path / f"{axis}.tlog").loops[0]
    r, p = res[Loop.ROLL], res[Loop.PITCH]
    assert r.identification is not None and p.identification is not None
    pr, pp = pooled_attitude(r.identification, p.identification)
    if pr is r.identification:
        pytest.skip("this draw's phase at the cycle cannot be met by a T1: nothing pooled")
    unpooled = dict(res)
    _pool_roll_pitch(res, {}, math.nan)
    for lp, design in ((Loop.ROLL, pr), (Loop.PITCH, pp)):
        got = res[lp]
        assert got.identification is unpooled[lp].identification  # reported as identified
        assert got.cycles is not None
        want = robust_onboard_gains(design, _gcs_delay(got.segment, got.cycles[0]))
        assert got.gains == want.gains and got.gcs_delay_s == want.delay_s
        assert got.gains != unpooled[lp].gains
        assert sum("pooled" in n for n in got.notes) == 1, got.notes
        assert sum(n.startswith("gains re-targeted") for n in got.notes) == 1, got.notes
