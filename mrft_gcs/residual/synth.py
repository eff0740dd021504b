"""Relay records from the bundled SITL physics, for tests and benchmarks of residual analysis.

:func:`sitl_relay_record` flies one MRFT on the 6-DOF physics of
:mod:`mrft_gcs.sitl.physics` in-process (no MAVLink), at the relay's own sample
time, with the airframe's sensor noise and any unmodelled effects switched on.
Nothing in the record says which effects were on: the analysis gets the record,
the relay settings and the airframe's *linear* models, as a user would.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from mrft_gcs.plant import InnerModel
from mrft_gcs.relay import MRFT
from mrft_gcs.sitl.airframe import Airframe, load_airframe
from mrft_gcs.sitl.physics import Multirotor

__all__ = ["RelayRecord", "sitl_relay_record", "write_relay_tlog"]


@dataclass(frozen=True)
class RelayRecord:
    """One relay test: samples, the relay that ran and the airframe's true linear model."""

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    beta: float
    h: float
    bias: float
    band: float
    model: InnerModel
    hover: float


def sitl_relay_record(loop: str = "roll", *, vehicle: str | Airframe = "qdrone",
                      effects: dict[str, float] | None = None, beta: float = -0.5,
                      h: float = 0.08, duration_s: float = 8.0, rate_hz: float = 250.0,
                      seed: int = 0, noise: bool = True, band: float | None = None,
                      relay_bias: float = 0.0) -> RelayRecord:
    """Fly an MRFT on ``loop`` (``roll``, ``pitch`` or ``altitude``) of the SITL physics.

    ``effects`` maps SITL effect names (:data:`mrft_gcs.sitl.EFFECT_NAMES`) to values;
    ``input_bias`` adds a torque bias on the tested axis (normalised) or, on altitude,
    an error of the hover command; ``extra_delay`` lengthens the measurement delay (s).
    The returned ``model`` is the airframe's linear model *without* these effects.

    Attitude loops drive the normalised torque at hover thrust; the altitude loop drives
    the collective command's deviation from the hover command, from 5 m up. ``band``
    defaults to four times the sensor noise; ``relay_bias`` is the relay's own (declared)
    bias, its output is ``relay_bias +- h``.
    """
    af = load_airframe(vehicle) if isinstance(vehicle, str) else vehicle
    if not noise:
        af = af.quiet()
    lin = af.linear_models()[loop]
    model = InnerModel(lin["K"], lin["T_prop"], lin["T1"], lin["tau"])
    effects = dict(effects or {})
    # ``input_bias``: a torque bias on the tested axis, or a hover-thrust error on altitude.
    in_bias = float(effects.pop("input_bias", 0.0))
    if in_bias and loop != "altitude":
        axis = 0 if loop == "roll" else 1
        tb = list(af.torque_bias)
        tb[axis] += in_bias
        af = dataclasses.replace(af, torque_bias=(tb[0], tb[1], tb[2]))
    # ``extra_delay``: measurement delay the linear model does not have (s).
    extra = float(effects.pop("extra_delay", 0.0))
    if extra:
        name = "position_sensor_delay_s" if loop == "altitude" else "attitude_sensor_delay_s"
        af = dataclasses.replace(af, **{name: getattr(af, name) + extra})
    if effects:
        af = af.with_effects(effects)
    phys = Multirotor(af, seed=seed)
    phys.reset(position_ned=(0.0, 0.0, -5.0), airborne=True)
    hover_cmd = phys._thrust_to_cmd(af.hover_thrust) + (in_bias if loop == "altitude" else 0.0)
    sigma = af.position_noise_m if loop == "altitude" else af.attitude_noise_rad
    band = 4.0 * sigma if band is None else band
    relay = MRFT(beta, h, relay_bias, band)
    sub = max(1, int(round(1.0 / (rate_hz * phys.dt))))
    n = int(round(duration_s * rate_hz))
    t, u, y = np.empty(n), np.empty(n), np.empty(n)
    y0 = None
    for k in range(n):
        m = phys.meas
        if loop == "altitude":
            val = -m.position_ned[2]
        elif loop == "roll":
            val = m.roll
        else:
            val = m.pitch
        if y0 is None:
            y0 = val
        cmd = float(relay.step(y0 - val)[0])
        t[k], u[k], y[k] = m.time_s, cmd, val
        for _ in range(sub):
            if loop == "altitude":
                phys.step(0.0, 0.0, 0.0, hover_cmd + cmd)
            elif loop == "roll":
                phys.step(cmd, 0.0, 0.0, hover_cmd)
            else:
                phys.step(0.0, cmd, 0.0, hover_cmd)
    return RelayRecord(t, u, y, beta, h, relay_bias, band, model, af.hover_thrust)


def write_relay_tlog(path, loop: str, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                     t_wall0: float = 1_700_000_000.0,
                     params: dict[str, float] | None = None) -> None:
    """Write a relay test as a .tlog: the vehicle's ATTITUDE / LOCAL_POSITION_NED carrying
    ``y`` and the ground station's SET_ACTUATOR_CONTROL_TARGET carrying ``u``.

    ``loop`` is ``roll``, ``pitch`` or ``altitude`` (``u`` the collective thrust then).
    ``params``: PARAM_VALUE messages the vehicle sends before the test (name -> value).
    """
    from pymavlink.dialects.v20 import common as mav

    from mrft_gcs.logs import TlogWriter

    veh = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    t = np.asarray(t, float) - float(t[0])
    with TlogWriter(path, overwrite=True) as w:
        w.write(veh.heartbeat_encode(2, 12, 137, 6 << 16, 4, 3).pack(veh), t_wall0)
        for i, (name, value) in enumerate((params or {}).items()):
            w.write(veh.param_value_encode(name.encode(), value, 9, len(params or {}), i)
                    .pack(veh), t_wall0)
        for k in range(t.size):
            boot_ms = int(round(5000 + t[k] * 1000))
            wall = t_wall0 + t[k]
            roll = float(y[k]) if loop == "roll" else 0.0
            pitch = float(y[k]) if loop == "pitch" else 0.0
            z = -float(y[k]) if loop == "altitude" else -5.0
            w.write(veh.attitude_encode(boot_ms, roll, pitch, 0.0, 0.0, 0.0, 0.0).pack(veh),
                    wall + 0.0005)
            w.write(veh.local_position_ned_encode(boot_ms, 0.0, 0.0, z, 0.0, 0.0, 0.0).pack(veh),
                    wall + 0.0005)
            ctl = [0.0] * 8
            ctl[3] = 0.45
            if loop == "altitude":
                ctl[3] = 0.45 + float(u[k])
            else:
                ctl[0 if loop == "roll" else 1] = float(u[k])
            w.write(gcs.set_actuator_control_target_encode(0, 0, 1, 1, ctl).pack(gcs),
                    wall + 0.0008)
            if k % 250 == 0:
                w.write(veh.heartbeat_encode(2, 12, 137, 6 << 16, 4, 3).pack(veh), wall)
