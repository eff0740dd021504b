"""Link loss during the zero-gain window on a real ArduCopter (its SITL build), with and
without the tool's Lua guard (``mrft_gcs.link.failsafe``).

    python benchmarks/linkloss_ardupilot.py [--instance N] [--json PATH]
                                            [--case none:0.1 --case 0.5:0.1 ...]

Each case boots a fresh SITL (parameters wiped, SCR_ENABLE 1), takes off on the stock gains
in GUIDED_NOGPS to 2 m (level SET_ATTITUDE_TARGET, raw thrust), then in one burst writes the
feed-forward set of issue 23 (ATC_RAT_*_P/I/D/D_FF/FLTT/NTF 0, ATC_RAT_*_FF 0.1/0.1/0.2,
ATC_ANG_*_P 0, ATC_ACCEL_*_MAX 0, ATC_RATE_FF_ENAB 1, ...), sends one last body-rate command
(roll rate ``R`` rad/s, attitude ignored: what a relay test leaves behind) and closes the
link. ``--profile-set`` writes the ardupilot profile's rate-path set instead (k 1,
GUID_TIMEOUT 0.2 s: what the tool flies). A case ``S:R`` installs the guard with silence
``S`` s first; ``none:R`` does not.
An observer on SERIAL1 (system id 254, not a ground-station id) records the largest tilt,
when the guard spoke, the touch-down speed the SITL reports ("SIM Hit ground at") and
whether the vehicle disarmed within 25 s.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

from mrft_gcs.link import VehicleLink
from mrft_gcs.link.failsafe import install_link_loss_guard
from mrft_gcs.link.modes import ARDUPILOT_COPTER_MODES
from mrft_gcs.params import ParamClient
from mrft_gcs.profiles import load_profile
from mrft_gcs.sitl.arducopter import ArduCopterSitl, fly_level, why_not
from mrft_gcs.telemetry import (
    Attitude,
    Heartbeat,
    RateTarget,
    StatusText,
)

ZERO_SET: dict[str, float] = {
    **{f"ATC_RAT_{a}_{k}": 0.0 for a in ("RLL", "PIT", "YAW")
       for k in ("P", "I", "D", "D_FF", "FLTT", "NTF")},
    "ATC_RAT_RLL_FF": 0.1, "ATC_RAT_PIT_FF": 0.1, "ATC_RAT_YAW_FF": 0.2,
    **{f"ATC_ANG_{a}_P": 0.0 for a in ("RLL", "PIT", "YAW")},
    **{f"ATC_ACCEL_{a}_MAX": 0.0 for a in "RPY"},
    "ATC_RATE_FF_ENAB": 1, "ACRO_RP_RATE_TC": 0, "PILOT_Y_RATE_TC": 0, "ATC_ANGLE_BOOST": 0,
    "MOT_BAT_VOLT_MAX": 0, "ATC_THR_G_BOOST": 0, "ACRO_BAL_ROLL": 0, "ACRO_BAL_PITCH": 0,
}
MAV_PARAM_TYPE_REAL32 = 9


def run_case(base: int, silence_s: float | None, roll_rate: float) -> dict[str, object]:
    serial0, serial1 = f"tcp:127.0.0.1:{base}", f"tcp:127.0.0.1:{base + 2}"
    out: dict[str, object] = {"silence_s": silence_s, "last_roll_rate_rad_s": roll_rate,
                              "params_written": len(ZERO_SET)}
    with VehicleLink.connect(serial1, timeout_s=10, source_system=254) as obs:
        backup = {n: p.value for n, p in ParamClient(obs).read_many(ZERO_SET).items()}
        obs.request_message_interval("ATTITUDE", 50.0)
        with obs.subscribe(StatusText, Attitude, Heartbeat) as events:
            link = VehicleLink.connect(serial0, timeout_s=10)
            try:
                if silence_s is not None:
                    install_link_loss_guard(link, backup, silence_s)
                link.request_message_interval("LOCAL_POSITION_NED", 50.0)
                link.set_mode(ARDUPILOT_COPTER_MODES["offboard"])
                link.arm()
                if fly_level(link, 30.0, until_m=1.8) < 1.8:
                    raise RuntimeError(f"no take-off in 30 s (armed {link.heartbeat.armed})")
                out["altitude_m"] = round(fly_level(link, 2.0), 2)
                while events.get(0.0) is not None:
                    pass
                for name, value in ZERO_SET.items():  # a burst, no read-back: no time passes
                    link.send_param_set(name, value, MAV_PARAM_TYPE_REAL32)
                for _ in range(5):
                    link.send_rate_target(RateTarget(0.0, roll_rate, 0.0, 0.0, 0.37))
                    time.sleep(0.02)
            finally:
                link.close()
            t0 = time.monotonic()
            tilt = 0.0
            while time.monotonic() - t0 < 25.0:
                e = events.get(0.5)
                t = round(time.monotonic() - t0, 2)
                if isinstance(e, Attitude):
                    c = math.cos(e.roll_rad) * math.cos(e.pitch_rad)
                    tilt = max(tilt, math.degrees(math.acos(max(-1.0, min(1.0, c)))))
                elif isinstance(e, StatusText) and e.text.startswith("mrftguard"):
                    out.update(guard_s=t, guard_text=e.text, tilt_at_guard_deg=round(tilt, 1))
                elif isinstance(e, StatusText) and e.text.startswith("SIM Hit ground at"):
                    out.update(touchdown_s=t, touchdown_m_s=round(float(e.text.split()[4]), 2))
                elif isinstance(e, Heartbeat) and not e.armed:
                    out["disarmed_s"] = t
                    break
            out["max_tilt_deg"] = round(tilt, 1)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instance", type=int, default=5)
    ap.add_argument("--case", action="append", help="SILENCE_S:ROLL_RATE or none:ROLL_RATE")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--profile-set", action="store_true",
                    help="write the ardupilot profile's [rate_path.test_params] (k 1, "
                         "GUID_TIMEOUT 0.2 s) instead of issue 23's probe set")
    args = ap.parse_args()
    if args.profile_set:
        rate_path = load_profile("ardupilot").rate_path
        assert rate_path is not None
        ZERO_SET.clear()
        ZERO_SET.update(rate_path.test_params)
    if (reason := why_not()) is not None:
        print(f"error: {reason}", file=sys.stderr)
        return 2
    cases = args.case or ["none:0.1", "1.0:0.1", "0.5:0.1", "0.5:0.3", "0.3:0.3", "none:0.3"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in cases:
            silence, rate = case.split(":")
            # a SITL that did not get ready is not fit for the case: it raises
            with ArduCopterSitl.start(args.instance, Path(tmp) / "run", {"SCR_ENABLE": 1},
                                      require_ready=True) as sitl:
                row = run_case(sitl.base_port,
                               None if silence == "none" else float(silence), float(rate))
            print(json.dumps(row), flush=True)
            rows.append(row)
    if args.json:
        args.json.write_text(json.dumps({"load_avg_1min": os.getloadavg()[0], "runs": rows},
                                        indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
