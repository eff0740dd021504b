"""Probe PX4's rate loop as a torque channel: real PX4 SITL (SIH quad-x), MAVLink only.

With MC_{ROLL,PITCH,YAW}RATE_P/I/D = 0 and MC_*RATE_FF = k, a body-rate set point ``w`` of
SET_ATTITUDE_TARGET (attitude ignored, OFFBOARD) should come out of PX4's rate controller as
the normalised torque ``k w``. This script flies the SITL with all attitude control on a
ground-station PD (250 Hz) sent through that channel and prints what it measured:

* the parameters' stock values and what the arming checks say with the test values written;
* take-off and hover with attitude on the ground station (max tilt, altitude);
* from PX4's own log (ulog, pyulog): torque set point vs ``FF * rate set point`` per sample,
  the set point to torque delay, whether the attitude controller ran (vehicle_control_mode);
* link loss: the set points stop for ``--loss-s`` seconds in hover; what PX4 does (mode,
  tilt, altitude) with the rate gains at zero.

Run it through the team lock (it starts its own PX4 process and stops it)::

    flock /tmp/team/live.lock python benchmarks/probe_px4_rate.py --json out.json
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from mrft_gcs.sitl.px4sitl import BINARY, Px4Sitl, free_instance, why_not

AXES = ("ROLL", "PITCH", "YAW")
#: parameters read and reported (stock values)
REPORTED = [f"MC_{a}RATE_{t}" for a in AXES for t in ("P", "I", "D", "FF", "K")] + [
    "MC_ROLL_P", "MC_PITCH_P", "MC_YAW_P", "MC_ROLLRATE_MAX", "MC_PITCHRATE_MAX",
    "MC_YAWRATE_MAX", "MC_AIRMODE", "MC_BAT_SCALE_EN", "IMU_GYRO_CUTOFF", "IMU_DGYRO_CUTOFF",
    "IMU_GYRO_RATEMAX", "COM_OF_LOSS_T", "COM_OBL_RC_ACT", "COM_RC_IN_MODE", "NAV_DLL_ACT",
    "MPC_THR_HOVER", "SDLOG_MODE", "SDLOG_PROFILE"]
_INT_TYPES = (mavutil.mavlink.MAV_PARAM_TYPE_INT8, mavutil.mavlink.MAV_PARAM_TYPE_INT16,
              mavutil.mavlink.MAV_PARAM_TYPE_INT32, mavutil.mavlink.MAV_PARAM_TYPE_UINT8,
              mavutil.mavlink.MAV_PARAM_TYPE_UINT16, mavutil.mavlink.MAV_PARAM_TYPE_UINT32)
#: type_mask of SET_ATTITUDE_TARGET: attitude ignored, body rates + thrust used
ATTITUDE_IGNORE = 128
OFFBOARD_MAIN = 6
#: vehicle_status.nav_state of OFFBOARD
NAV_OFFBOARD = 14
POSCTL_MAIN = 3


class Link:
    """Raw pymavlink on PX4's offboard link (PX4 sends at its onboard-mode rates)."""

    def __init__(self, sitl: Px4Sitl) -> None:
        self.conn = mavutil.mavlink_connection(sitl.offboard, source_system=255,
                                               source_component=190)
        self.sysid = sitl.system_id
        self.types: dict[str, int] = {}
        self.texts: list[tuple[float, str]] = []
        self.att: Any = None
        self.pos: Any = None
        self.mode: tuple[int, int] = (0, 0)
        self.armed = False
        self.t0 = time.monotonic()
        self._beat = 0.0
        if self.conn.wait_heartbeat(timeout=30) is None:
            raise RuntimeError("no heartbeat on the PX4 offboard link")
        for msg_id, hz in ((30, 250), (32, 50), (83, 50)):
            self.command(mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)

    def now(self) -> float:
        return time.monotonic() - self.t0

    def pump(self, timeout: float = 0.0) -> list:
        """Read everything waiting (and wait up to ``timeout`` for the first message)."""
        got: list[Any] = []
        end = time.monotonic() + timeout
        while True:
            if time.monotonic() - self._beat > 1.0:
                self.conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                             mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                self._beat = time.monotonic()
            msg = self.conn.recv_msg()
            if msg is None:
                if time.monotonic() >= end:
                    return got
                time.sleep(0.0005)
                continue
            if msg.get_srcSystem() != self.sysid:
                continue
            kind = msg.get_type()
            if kind == "ATTITUDE":
                self.att = msg
            elif kind == "LOCAL_POSITION_NED":
                self.pos = msg
            elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
                self.mode = ((msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF)
                self.armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "STATUSTEXT":
                self.texts.append((self.now(), msg.text))
                print(f"  [{self.now():6.2f}] PX4: {msg.text}")
            got.append(msg)

    def wait(self, kind: str, cond, timeout: float):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in self.pump(0.05):
                if m.get_type() == kind and cond(m):
                    return m
        return None

    def command(self, cmd: int, *p: float, timeout: float = 3.0) -> int | None:
        args = list(p) + [0.0] * (7 - len(p))
        self.conn.mav.command_long_send(self.sysid, 1, cmd, 0, *args)
        ack = self.wait("COMMAND_ACK", lambda m: m.command == cmd, timeout)
        return None if ack is None else ack.result

    def get(self, name: str) -> float:
        self.conn.mav.param_request_read_send(self.sysid, 1, name.encode(), -1)
        msg = self.wait("PARAM_VALUE", lambda m: m.param_id == name, 3.0)
        if msg is None:
            return math.nan
        self.types[name] = msg.param_type
        return self._decode(msg.param_value, msg.param_type)

    @staticmethod
    def _decode(value: float, ptype: int) -> float:
        if ptype in _INT_TYPES:  # PX4 sends integers bytewise in the float field
            return float(struct.unpack("<i", struct.pack("<f", value))[0])
        return value

    def set(self, name: str, value: float) -> float:
        if name not in self.types:
            self.get(name)
        ptype = self.types[name]
        wire = (struct.unpack("<f", struct.pack("<i", int(round(value))))[0]
                if ptype in _INT_TYPES else value)
        for _ in range(3):
            self.conn.mav.param_set_send(self.sysid, 1, name.encode(), wire, ptype)
            msg = self.wait("PARAM_VALUE", lambda m: m.param_id == name, 2.0)
            if msg is not None:
                back = self._decode(msg.param_value, ptype)
                if abs(back - value) <= 1e-6 * max(1.0, abs(value)):
                    return back
        raise RuntimeError(f"{name} = {value} not read back")

    def send_rates(self, rates: tuple[float, ...], thrust: float) -> None:
        self.conn.mav.set_attitude_target_send(
            int(self.now() * 1000) & 0xFFFFFFFF, self.sysid, 1, ATTITUDE_IGNORE,
            [1.0, 0.0, 0.0, 0.0], rates[0], rates[1], rates[2], thrust)


class GroundPD:
    """Attitude PD on the ground station, torque sent as rate / k; altitude PID on thrust."""

    def __init__(self, k: tuple[float, float, float], hover: float) -> None:
        self.k = k
        self.hover = hover
        # torque per rad and per rad/s (normalised): about PX4's stock cascade, softer
        self.kp = (0.5, 0.5, 0.3)
        self.kd = (0.08, 0.08, 0.2)
        self.alt_i = 0.0
        self.yaw0: float | None = None

    def step(self, link: Link, alt_sp: float, dt: float) -> tuple[tuple[float, ...], float]:
        a, p = link.att, link.pos
        if a is None or p is None:
            return (0.0, 0.0, 0.0), 0.0
        if self.yaw0 is None:
            self.yaw0 = a.yaw
        yaw_err = math.remainder(a.yaw - self.yaw0, 2 * math.pi)
        ang = (a.roll, a.pitch, yaw_err)
        rate = (a.rollspeed, a.pitchspeed, a.yawspeed)
        torque = [-self.kp[i] * ang[i] - self.kd[i] * rate[i] for i in range(3)]
        alt, climb = -p.z, -p.vz
        err = alt_sp - alt
        self.alt_i = float(np.clip(self.alt_i + 0.08 * err * dt, -0.15, 0.15))
        thrust = float(np.clip(self.hover + 0.12 * err - 0.10 * climb + self.alt_i, 0.05, 0.9))
        # level thrust: PX4 takes thrust along body z, the GCS wants its vertical component
        thrust /= max(0.7, math.cos(a.roll) * math.cos(a.pitch))
        return tuple(torque[i] / self.k[i] for i in range(3)), min(thrust, 0.95)


def fly(link: Link, ctrl: GroundPD, seconds: float, alt_sp_of, log: list, rate_hz: float = 250,
        silent: tuple[float, float] | None = None) -> None:
    """Run the ground-station loop for ``seconds``; no set points inside ``silent`` (s)."""
    t_start = link.now()
    period = 1.0 / rate_hz
    next_t = time.monotonic()
    asked_back = False
    while (t := link.now() - t_start) < seconds:
        link.pump()
        rates, thrust = ctrl.step(link, alt_sp_of(t), period)
        quiet = silent is not None and silent[0] <= t < silent[1]
        if not quiet:
            link.send_rates(rates, thrust)
            if silent is not None and t >= silent[1] and link.mode[0] != OFFBOARD_MAIN \
                    and not asked_back:
                # back to OFFBOARD once the set points flow again (no wait for the ack)
                link.conn.mav.command_long_send(link.sysid, 1,
                                                mavutil.mavlink.MAV_CMD_DO_SET_MODE, 0, 1,
                                                OFFBOARD_MAIN, 0, 0, 0, 0, 0)
                asked_back = True
        a, p = link.att, link.pos
        if a is not None and p is not None:
            log.append((link.now(), a.roll, a.pitch, a.yaw, -p.z, link.mode[0], link.mode[1],
                        int(link.armed), int(quiet)))
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            next_t = time.monotonic()


def _loss_from_log(data: dict, t_sp: np.ndarray) -> dict:
    """When PX4 left OFFBOARD after the set points stopped, and the tilt from then on."""
    vs, att = data["vehicle_status"], data["vehicle_attitude"]
    nav, t_nav = vs["nav_state"], vs["timestamp"]
    left = np.nonzero((nav[:-1] == NAV_OFFBOARD) & (nav[1:] != NAV_OFFBOARD))[0]
    if not left.size:
        return {"left_offboard": False}
    t_left = t_nav[left[0] + 1]
    before = t_sp[t_sp < t_left]
    t_last = before[-1] if before.size else t_left
    # a gap in the set points longer than 0.1 s ends where the silence began
    gaps = np.nonzero(np.diff(before) > 100_000)[0]
    if gaps.size:
        t_last = before[gaps[-1]]
    qx, qy = att["q[1]"], att["q[2]"]
    tilt = np.degrees(np.arccos(np.clip(1 - 2 * (qx * qx + qy * qy), -1, 1)))
    t_att = att["timestamp"]

    def tilt_at(t: float) -> float:
        return float(tilt[min(np.searchsorted(t_att, t), len(tilt) - 1)])

    after = (t_att >= t_last) & (t_att <= t_last + 3_000_000)
    over = {}
    for deg in (10, 30, 60):
        hit = np.nonzero(after & (tilt >= deg))[0]
        over[f"tilt_{deg}_after_s"] = float((t_att[hit[0]] - t_last) * 1e-6) if hit.size \
            else None
    return {"left_offboard": True, "to_nav_state": int(nav[left[0] + 1]),
            "after_last_setpoint_s": float((t_left - t_last) * 1e-6),
            "tilt_at_last_setpoint_deg": tilt_at(t_last),
            "tilt_at_mode_change_deg": tilt_at(t_left),
            "tilt_max_3s_deg": float(np.max(tilt[after])) if after.any() else None, **over}


#: how far back a torque sample is matched against the logged rate set points (us)
MATCH_WINDOW_US = 12_000


def _match(sp: dict, tq: dict, ff: tuple[float, float, float], status: dict | None) -> dict:
    t_sp, t_tq = sp["timestamp"].astype(np.int64), tq["timestamp"].astype(np.int64)
    want = np.stack([np.float32(ff[i]) * sp[k] for i, k in enumerate(("roll", "pitch", "yaw"))],
                    axis=1)
    got = np.stack([tq[f"xyz[{i}]"] for i in range(3)], axis=1)
    rows = np.arange(len(t_tq))
    if status is not None:  # OFFBOARD only: elsewhere PX4's attitude loop makes the set point
        j = np.clip(np.searchsorted(status["timestamp"], t_tq, side="right") - 1, 0, None)
        rows = rows[status["nav_state"][j] == NAV_OFFBOARD]
    lags = []
    for i in rows:
        lo = np.searchsorted(t_sp, t_tq[i] - MATCH_WINDOW_US, side="left")
        hi = np.searchsorted(t_sp, t_tq[i], side="right")
        same = np.nonzero(np.all(want[lo:hi] == got[i], axis=1))[0]
        lags.append(t_tq[i] - t_sp[lo + same[-1]] if same.size else -1)
    lag = np.array(lags)
    hit = lag >= 0
    steps, counts = np.unique(lag[hit] // 1000, return_counts=True)
    gaps = np.diff(t_sp)
    return {"offboard_torque_samples": int(len(rows)),
            "equal_share": float(np.mean(hit)) if len(rows) else math.nan,
            "lag_ms_counts": {int(k): int(c) for k, c in zip(steps, counts, strict=True)},
            "setpoint_log_gaps_over_4ms": int(np.sum(gaps > 4000)),
            "max_abs_torque": float(np.max(np.abs(got[rows]))) if len(rows) else math.nan}


def analyse_ulog(path: Path, ff: tuple[float, float, float]) -> dict:
    """Torque set point vs FF * rate set point, delay and flags from PX4's own log."""
    from pyulog import ULog

    ulog = ULog(str(path), ["vehicle_rates_setpoint", "vehicle_torque_setpoint",
                            "vehicle_control_mode", "rate_ctrl_status", "vehicle_status",
                            "vehicle_attitude"])
    data = {d.name: d.data for d in ulog.data_list if d.multi_id == 0}
    sp, tq = data["vehicle_rates_setpoint"], data["vehicle_torque_setpoint"]
    t_sp = sp["timestamp"]
    out: dict = {"log": str(path)}
    # PX4's SITL clock steps in gyro periods (4 ms with SIH), so a set point and the torque
    # computed from it can carry the same or the next step's time stamp: each OFFBOARD torque
    # sample is matched, bitwise on all three axes, against FF x the set points logged in the
    # MATCH_WINDOW_US before it; the lag is the distance to the one it equals
    out["torque_equals_ff_setpoint"] = _match(sp, tq, ff, data.get("vehicle_status"))
    out["torque_rate_hz"] = float(1e6 / np.median(np.diff(tq["timestamp"])))
    out["rates_sp_rate_hz"] = float(1e6 / np.median(np.diff(t_sp)))
    if "vehicle_control_mode" in data:
        cm = data["vehicle_control_mode"]
        off = cm["flag_control_offboard_enabled"] == 1
        out["attitude_ctrl_in_offboard"] = sorted(
            {int(v) for v in cm["flag_control_attitude_enabled"][off]})
        out["rates_ctrl_in_offboard"] = sorted(
            {int(v) for v in cm["flag_control_rates_enabled"][off]})
    if "vehicle_status" in data and "vehicle_attitude" in data:
        out["link_loss"] = _loss_from_log(data, t_sp)
    if "rate_ctrl_status" in data:
        rs = data["rate_ctrl_status"]
        out["rate_integrator_max_abs"] = float(max(
            np.max(np.abs(rs[k])) for k in ("rollspeed_integ", "pitchspeed_integ",
                                            "yawspeed_integ")))
    return out


def high_rate_logging(link: Link, sitl: Px4Sitl, profile: int) -> str:
    """Restart PX4's logger with its high-rate profile (every set point and torque sample),
    through PX4's own command client; the stock profile logs them at 50 Hz only."""
    link.set("SDLOG_PROFILE", profile | 16)
    exe = str(BINARY.parent / "px4-logger")
    said = []
    for cmd in (["stop"], ["start", "-b", "1000", "-t", "-e"]):
        r = subprocess.run([exe, "--instance", str(sitl.instance), *cmd], cwd=sitl.run_dir,
                           capture_output=True, text=True, timeout=20)
        said.append(f"logger {cmd[0]}: rc {r.returncode}")
        time.sleep(0.5)
    return ", ".join(said)


def probe_values(k: float, zero_angle_p: bool, of_loss_t: float | None = None,
                 obl_act: int | None = None) -> dict[str, float]:
    """The parameters the probe writes: rate P/I/D 0, FF k (and angle P 0, loss settings)."""
    test: dict[str, float] = {}
    for a in AXES:
        test.update({f"MC_{a}RATE_P": 0.0, f"MC_{a}RATE_I": 0.0, f"MC_{a}RATE_D": 0.0,
                     f"MC_{a}RATE_FF": k})
        if zero_angle_p:
            test[f"MC_{a}_P"] = 0.0
    if of_loss_t is not None:
        test["COM_OF_LOSS_T"] = of_loss_t
    if obl_act is not None:
        test["COM_OBL_RC_ACT"] = obl_act
    return test


def probe_flight(sitl: Px4Sitl, test: Mapping[str, float], k: tuple[float, float, float], *,
                 alt: float = 2.0, hover_s: float = 8.0, loss_s: float = 0.0) -> dict:
    """On a running PX4 SITL: read the reported parameters, write ``test`` (read back),
    take off and hover on the ground-station PD through the rate feed-forward, optionally
    stop the set points for ``loss_s``, land, disarm; then PX4's log of the flight.

    Writes without a backup: meant for a SITL booted with factory parameters."""
    result: dict = {"boot_s": sitl.readiness.ready_s}
    link = Link(sitl)
    before = {n: link.get(n) for n in REPORTED}
    result["before"] = before
    result["high_rate_log"] = high_rate_logging(link, sitl, int(before["SDLOG_PROFILE"]))
    t_write = time.monotonic()
    for name, value in test.items():
        link.set(name, value)
    result["written"] = dict(test)
    result["write_s"] = time.monotonic() - t_write
    link.pump(2.0)  # let arming checks re-run on the new values
    sys_status = link.wait("SYS_STATUS", lambda m: True, 3.0)
    result["prearm_ok_with_test_values"] = bool(
        sys_status and sys_status.onboard_control_sensors_health & 0x10000000)
    ctrl = GroundPD(k, hover=before["MPC_THR_HOVER"] if before["MPC_THR_HOVER"] > 0 else 0.5)
    log: list = []
    # OFFBOARD needs a set point stream before the switch
    fly(link, ctrl, 1.0, lambda t: 0.0, log)
    ack_mode = link.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, OFFBOARD_MAIN, 0)
    ack_arm = link.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    result["offboard_ack"], result["arm_ack"] = ack_mode, ack_arm
    texts_before = len(link.texts)
    fly(link, ctrl, 4.0, lambda t: min(alt, 0.2 + alt * t / 3.0), log)
    t_hover0 = link.now()
    fly(link, ctrl, hover_s, lambda t: alt, log)
    arr = np.array(log)
    hov = arr[arr[:, 0] >= t_hover0]
    result["hover"] = {
        "seconds": hover_s,
        "max_abs_roll_deg": float(np.degrees(np.max(np.abs(hov[:, 1])))),
        "max_abs_pitch_deg": float(np.degrees(np.max(np.abs(hov[:, 2])))),
        "yaw_span_deg": float(np.degrees(np.ptp(np.unwrap(hov[:, 3])))),
        "alt_mean_m": float(np.mean(hov[:, 4])), "alt_min_m": float(np.min(hov[:, 4])),
        "alt_max_m": float(np.max(hov[:, 4])),
        "mode_main": sorted({int(v) for v in hov[:, 5]}),
        "armed_all": bool(np.all(hov[:, 7] == 1)),
    }
    if loss_s > 0:
        t_loss0 = link.now()
        fly(link, ctrl, loss_s + 3.0, lambda t: alt, log, silent=(0.0, loss_s))
        arr = np.array(log)
        seg = arr[arr[:, 0] >= t_loss0]
        tilt = np.degrees(np.arccos(np.clip(np.cos(seg[:, 1]) * np.cos(seg[:, 2]), -1, 1)))
        change = np.nonzero(seg[:, 5] != OFFBOARD_MAIN)[0]
        result["link_loss"] = {
            "silent_s": loss_s,
            "mode_change_seen_after_s": float(seg[change[0], 0] - t_loss0) if change.size
            else None,
            "modes_seen": sorted({(int(m), int(s)) for m, s in seg[:, 5:7]}),
            "max_tilt_deg": float(np.max(tilt)),
            "max_tilt_at_s": float(seg[int(np.argmax(tilt)), 0] - t_loss0),
            "alt_min_m": float(np.min(seg[:, 4])),
            "offboard_again_at_end": bool(seg[-1, 5] == OFFBOARD_MAIN),
            "armed_at_end": bool(seg[-1, 7] == 1),
        }
    result["statustext_in_flight"] = [t for _, t in link.texts[texts_before:]]
    # land on the ground-station loop, then disarm
    result["landed_on_gcs_loop"] = link.mode[0] == OFFBOARD_MAIN and link.armed
    if result["landed_on_gcs_loop"]:
        fly(link, ctrl, 4.0, lambda t: max(-0.5, alt * (1 - t / 3.0)), log)
    link.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)
    link.pump(1.5)
    link.conn.close()
    logs = sorted((sitl.run_dir / "log").rglob("*.ulg"), key=lambda p: p.stat().st_mtime)
    if logs:
        try:
            result["ulog"] = analyse_ulog(logs[-1], k)
        except Exception as exc:  # a truncated log: report, keep the MAVLink figures
            result["ulog"] = {"error": f"{type(exc).__name__}: {exc}", "log": str(logs[-1])}
    else:
        result["ulog"] = {"error": f"no .ulg under {sitl.run_dir / 'log'}"}
    return result


def flight(args: argparse.Namespace, zero_angle_p: bool) -> dict:
    """One SITL boot with factory parameters, one probe flight, the SITL stopped."""
    test = probe_values(args.k, zero_angle_p, args.of_loss_t, args.obl_act)
    with Px4Sitl.start(free_instance(), Path(tempfile.mkdtemp(prefix="px4rate_"))) as sitl:
        result = probe_flight(sitl, test, (args.k, args.k, args.k), alt=args.alt,
                              hover_s=args.hover_s, loss_s=args.loss_s)
    return {"zero_angle_p": zero_angle_p, **result}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=float, default=1.0, help="MC_*RATE_FF written (torque/(rad/s))")
    ap.add_argument("--alt", type=float, default=2.0, help="hover altitude (m)")
    ap.add_argument("--hover-s", type=float, default=8.0)
    ap.add_argument("--loss-s", type=float, default=2.0,
                    help="set points stop this long in hover (0: no link-loss test)")
    ap.add_argument("--angle-p", choices=("stock", "zero", "both"), default="both",
                    help="MC_*_P left stock, zeroed, or one flight each")
    ap.add_argument("--of-loss-t", type=float, default=None,
                    help="COM_OF_LOSS_T written for the flight (s; default: PX4's)")
    ap.add_argument("--obl-act", type=int, default=None,
                    help="COM_OBL_RC_ACT written for the flight (default: PX4's)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    reason = why_not()
    if reason is not None:
        print(f"skip: {reason}")
        return 2
    runs = {"stock": [False], "zero": [True], "both": [False, True]}[args.angle_p]
    results = []
    for zero in runs:
        print(f"== flight: MC_*_P {'zero' if zero else 'stock'}, MC_*RATE_FF = {args.k}")
        r = flight(args, zero)
        print(json.dumps(r, indent=1, default=str))
        results.append(r)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
