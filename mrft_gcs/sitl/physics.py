"""6-DOF multirotor physics with motors, delays, sensors and switchable unmodelled effects.

One :class:`Multirotor` steps at a fixed ``dt_s`` (1 ms by default) from normalised commands
(roll, pitch, yaw torque in [-1, 1], collective thrust in [0, 1]) to a measured state:

``commands -> [dead band, rate limit, bias] -> mixer -> clip -> actuator delay
-> motor speed lag (thrust ~ speed^2) -> forces and moments -> rigid body (quaternion)
-> ground contact -> sensor delay -> noise -> [low-pass] -> measurement``

Frames: world NED, body FRD; the quaternion ``q = (w, x, y, z)`` rotates body to world.
The mixer is linear with coefficients ``+-0.5`` so that a torque command of 1 gives the largest
moment the motors can produce about that axis (see :mod:`mrft_gcs.sitl.airframe`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrft_gcs.sitl.airframe import GRAVITY_M_S2, Airframe
from mrft_gcs.telemetry import quat_from_euler

__all__ = ["Multirotor", "Measurement", "quat_from_euler", "euler_from_quat", "DT_S"]

DT_S = 0.001


def shaped_torques(roll: float, pitch: float, yaw: float, prev: tuple[float, ...],
                   effects, dt: float) -> tuple[float, float, float]:
    """Normalised torque commands as the motors deliver them: clipped to [-1, 1], through
    the airframe's motor dead zone and torque rate limit (``prev``: last step's, ``dt`` s)."""
    tq = [min(max(roll, -1.0), 1.0), min(max(pitch, -1.0), 1.0), min(max(yaw, -1.0), 1.0)]
    if effects.motor_deadzone:
        dz = effects.motor_deadzone
        tq = [math.copysign(max(abs(u) - dz, 0.0), u) for u in tq]
    if effects.torque_rate_limit:
        lim = effects.torque_rate_limit * dt
        tq = [p + min(max(u - p, -lim), lim) for u, p in zip(tq, prev, strict=True)]
    return tq[0], tq[1], tq[2]


def euler_from_quat(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """Unit quaternion to ZYX Euler angles ``(roll, pitch, yaw)`` in rad."""
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    s = max(-1.0, min(1.0, 2 * (w * y - z * x)))
    pitch = math.asin(s)
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


@dataclass(frozen=True)
class Measurement:
    """What the onboard sensors report (delayed, noisy, maybe filtered).

    Angles in rad (yaw wrapped to [-pi, pi]), rates in rad/s (body), position in m (NED),
    velocity in m/s (NED), specific force in m/s^2 (body), time in s since boot.
    """

    time_s: float
    roll: float
    pitch: float
    yaw: float
    rates: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]
    position_ned: tuple[float, float, float]
    velocity_ned: tuple[float, float, float]
    specific_force_body: tuple[float, float, float]
    on_ground: bool


class _Delay:
    """Fixed integer-step delay line (a ring of tuples)."""

    def __init__(self, steps: int, value: tuple[float, ...]) -> None:
        self.buf = [value] * (steps + 1)
        self.i = 0

    def push(self, value: tuple[float, ...]) -> tuple[float, ...]:
        buf = self.buf
        buf[self.i] = value
        self.i = (self.i + 1) % len(buf)
        return buf[self.i]  # the oldest sample: `steps` pushes ago


class Multirotor:
    """The simulated airframe: call :meth:`reset`, then :meth:`step` once per ``dt_s``.

    Plain Python floats inside (a 3-vector in numpy costs more than the arithmetic), so one
    step takes a few tens of microseconds and the vehicle runs in real time beside a GCS.

    Parameters
    ----------
    airframe : Airframe
    dt_s : float
        Fixed integration step (default 1 ms).
    seed : int
        Seed of the sensor-noise generator (same seed + same commands = same run).
    wind_m_s : (3,) float
        Constant wind in NED, m/s.

    Attributes
    ----------
    t : float
        Simulated time, s.
    on_ground : bool
    meas_att : tuple of 9 float
        Latest measured roll, pitch, yaw (continuous, not wrapped), body rates p, q, r and
        specific force (body); see :attr:`meas` for a typed snapshot.
    meas_posv : tuple of 6 float
        Latest measured NED position and velocity.
    """

    def __init__(self, airframe: Airframe, dt_s: float = DT_S, seed: int = 0,
                 wind_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        self.af = airframe
        self.dt = float(dt_s)
        self.seed = seed
        self.wind = tuple(float(w) for w in wind_m_s)
        eff = airframe.effects
        ms = airframe.motors
        self._n = len(ms)
        self._mix_roll = [-0.5 * math.copysign(1.0, y) if y else 0.0 for _, y, _ in ms]
        self._mix_pitch = [0.5 * math.copysign(1.0, x) if x else 0.0 for x, _, _ in ms]
        self._mix_yaw = [0.5 * s for _, _, s in ms]
        self._arm_x = [x - eff.com_offset for x, _, _ in ms]
        self._arm_y = [y - eff.com_offset for _, y, _ in ms]
        self._spin = [s for _, _, s in ms]
        self._tmax = airframe.motor_thrust_max_n
        self._kyaw = airframe.yaw_moment_per_thrust_m
        self._inertia = tuple(airframe.inertia_kg_m2)
        self._rot_drag = tuple(airframe.rot_drag_n_m_s_rad)
        self._lin_drag = tuple(airframe.lin_drag_n_s_m)
        self._alpha_motor = 1.0 - math.exp(-self.dt / airframe.motor_tau_s)
        self._lpf = (1.0 - math.exp(-2 * math.pi * eff.sensor_lpf * self.dt)
                     if eff.sensor_lpf > 0 else 1.0)
        self._att_noise = ((airframe.attitude_noise_rad,) * 3 + (airframe.gyro_noise_rad_s,) * 3
                           + (0.0,) * 3)
        self._pos_noise = (airframe.position_noise_m,) * 3 + (airframe.velocity_noise_m_s,) * 3
        self._noisy = any(self._att_noise) or any(self._pos_noise)
        self._bias = tuple(airframe.torque_bias)
        self.reset()

    def _steps(self, s: float) -> int:
        return max(0, int(round(s / self.dt)))

    # ------------------------------------------------------------------ state
    def reset(self, position_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
              yaw: float = 0.0, airborne: bool = False) -> None:
        """Put the vehicle at rest at ``position_ned``.

        With ``airborne=True`` the motors start at hover speed (for in-flight checks); otherwise
        the vehicle sits on the ground (z clamped to 0) with motors stopped.
        """
        af = self.af
        self.rng = np.random.default_rng(self.seed)
        self.t = 0.0
        px, py, pz = (float(v) for v in position_ned)
        if not airborne:
            pz = 0.0
        self._p = [px, py, pz]
        self._v = [0.0, 0.0, 0.0]
        self._q = list(quat_from_euler(0.0, 0.0, yaw))
        self._w = [0.0, 0.0, 0.0]
        self.on_ground = not airborne and pz >= 0.0
        hover = self._thrust_to_cmd(af.hover_thrust) if airborne else 0.0
        self.motor_cmd = (hover,) * self._n
        self.motor_speed = [math.sqrt(self._curve(hover))] * self._n
        self._torque_prev: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._sf = (0.0, 0.0, -GRAVITY_M_S2)
        self._yaw_unwrapped = yaw
        self._act_delay = _Delay(self._steps(af.actuator_delay_s), self.motor_cmd)
        att, posv = self._true_channels()
        self._att_delay = _Delay(self._steps(af.attitude_sensor_delay_s), att)
        self._pos_delay = _Delay(self._steps(af.position_sensor_delay_s), posv)
        self.meas_att, self.meas_posv = att, posv

    @property
    def pos(self) -> np.ndarray:
        """True NED position, m, shape (3,)."""
        return np.array(self._p)

    @property
    def vel(self) -> np.ndarray:
        """True NED velocity, m/s, shape (3,)."""
        return np.array(self._v)

    @property
    def quat(self) -> np.ndarray:
        """True attitude quaternion (w, x, y, z), shape (4,)."""
        return np.array(self._q)

    @property
    def rates(self) -> np.ndarray:
        """True body rates, rad/s, shape (3,)."""
        return np.array(self._w)

    @property
    def euler(self) -> tuple[float, float, float]:
        """True roll, pitch, yaw in rad."""
        return euler_from_quat(*self._q)

    def _curve(self, c: float) -> float:
        a = self.af.effects.thrust_curve
        return (1.0 - a) * c + a * c * c if a else c

    def _thrust_to_cmd(self, f: float) -> float:
        a = self.af.effects.thrust_curve
        if not a:
            return f
        return (-(1 - a) + math.sqrt((1 - a) ** 2 + 4 * a * f)) / (2 * a)

    def _true_channels(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        r, p, y = euler_from_quat(*self._q)
        # keep yaw continuous so that delay lines and filters never see a 2 pi jump
        dy = (y - self._yaw_unwrapped + math.pi) % (2 * math.pi) - math.pi
        self._yaw_unwrapped += dy
        att = (r, p, self._yaw_unwrapped, *self._w, *self._sf)
        return att, (*self._p, *self._v)

    # ------------------------------------------------------------------- step
    def step(self, roll: float, pitch: float, yaw: float, thrust: float) -> None:
        """Advance one step with normalised commands (held for ``dt_s``)."""
        af, eff, dt = self.af, self.af.effects, self.dt
        tq = shaped_torques(roll, pitch, yaw, self._torque_prev, eff, dt)
        self._torque_prev = tq
        b = self._bias
        tr, tp, ty = tq[0] + b[0], tq[1] + b[1], tq[2] + b[2]
        thrust = min(max(thrust, 0.0), 1.0)
        sat = eff.motor_saturation
        cmd = tuple(min(max(thrust + tr * a + tp * c + ty * d, 0.0), sat)
                    for a, c, d in zip(self._mix_roll, self._mix_pitch, self._mix_yaw, strict=True))
        self.motor_cmd = cmd
        delayed = self._act_delay.push(cmd)

        # motors: first-order lag on speed, thrust ~ speed^2
        am, tmax = self._alpha_motor, self._tmax
        curve = eff.thrust_curve
        spd = self.motor_speed
        total = mx = my = mz = 0.0
        for i in range(self._n):
            c = delayed[i]
            if curve:
                c = (1.0 - curve) * c + curve * c * c
            s = spd[i] + am * (math.sqrt(c) - spd[i])
            spd[i] = s
            f = tmax * s * s
            total += f
            mx -= self._arm_y[i] * f
            my += self._arm_x[i] * f
            mz += self._spin[i] * f
        mz *= self._kyaw

        w, x, y, z = self._q
        r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
        r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
        vx, vy, vz = self._v
        ax_, ay_, az_ = vx - self.wind[0], vy - self.wind[1], vz - self.wind[2]
        # air-relative velocity in body axes (R^T v)
        bx = r00 * ax_ + r10 * ay_ + r20 * az_
        by = r01 * ax_ + r11 * ay_ + r21 * az_
        bz = r02 * ax_ + r12 * ay_ + r22 * az_
        ld = self._lin_drag
        fx, fy, fz = -ld[0] * bx, -ld[1] * by, -ld[2] * bz - total
        if eff.quadratic_drag:
            k = eff.quadratic_drag * math.sqrt(bx * bx + by * by + bz * bz)
            fx, fy, fz = fx - k * bx, fy - k * by, fz - k * bz
        m = af.mass_kg
        acc_x = (r00 * fx + r01 * fy + r02 * fz) / m
        acc_y = (r10 * fx + r11 * fy + r12 * fz) / m
        acc_z = (r20 * fx + r21 * fy + r22 * fz) / m + GRAVITY_M_S2

        if self.on_ground and acc_z >= 0.0:
            # resting: the ground carries the weight
            self._v = [0.0, 0.0, 0.0]
            self._w = [0.0, 0.0, 0.0]
            g = GRAVITY_M_S2
            self._sf = (-r20 * g, -r21 * g, -r22 * g)
        else:
            self.on_ground = False
            self._sf = (fx / m, fy / m, fz / m)
            p, q, r = self._w
            ix, iy, iz = self._inertia
            dx, dy, dz = self._rot_drag
            # Euler's equations with linear rotational drag: I dw = M - b w - w x (I w)
            p_n = p + dt * (mx - dx * p - (q * iz * r - r * iy * q)) / ix
            q_n = q + dt * (my - dy * q - (r * ix * p - p * iz * r)) / iy
            r_n = r + dt * (mz - dz * r - (p * iy * q - q * ix * p)) / iz
            self._w = [p_n, q_n, r_n]
            vx, vy, vz = vx + acc_x * dt, vy + acc_y * dt, vz + acc_z * dt
            self._v = [vx, vy, vz]
            px, py, pz = self._p
            self._p = [px + vx * dt, py + vy * dt, pz + vz * dt]
            h = 0.5 * dt
            qw = w + h * (-x * p_n - y * q_n - z * r_n)
            qx = x + h * (w * p_n + y * r_n - z * q_n)
            qy = y + h * (w * q_n + z * p_n - x * r_n)
            qz = z + h * (w * r_n + x * q_n - y * p_n)
            nrm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            self._q = [qw / nrm, qx / nrm, qy / nrm, qz / nrm]
            if self._p[2] >= 0.0:  # touchdown: no bouncing, no falling through
                self._p[2] = 0.0
                self._v = [0.0, 0.0, 0.0]
                self._w = [0.0, 0.0, 0.0]
                _, _, yw = euler_from_quat(*self._q)
                self._q = list(quat_from_euler(0.0, 0.0, yw))
                self.on_ground = True
        self.t += dt
        self._sense()

    # ---------------------------------------------------------------- sensors
    def _sense(self) -> None:
        att, posv = self._true_channels()
        att = self._att_delay.push(att)
        posv = self._pos_delay.push(posv)
        if self._noisy:
            nz = self.rng.standard_normal(15).tolist()
            att = tuple(a + n * s for a, n, s in zip(att, nz[:9], self._att_noise, strict=True))
            posv = tuple(a + n * s for a, n, s in zip(posv, nz[9:], self._pos_noise, strict=True))
        if self._lpf < 1.0:
            k = self._lpf
            att = tuple(f + k * (a - f) for a, f in zip(att, self.meas_att, strict=True))
            posv = tuple(f + k * (a - f) for a, f in zip(posv, self.meas_posv, strict=True))
        self.meas_att, self.meas_posv = att, posv

    @property
    def meas(self) -> Measurement:
        """The latest measurement as a typed snapshot."""
        att, posv = self.meas_att, self.meas_posv
        r, p = att[0], att[1]
        y = (att[2] + math.pi) % (2 * math.pi) - math.pi
        return Measurement(
            time_s=self.t, roll=r, pitch=p, yaw=y, rates=(att[3], att[4], att[5]),
            quaternion=quat_from_euler(r, p, y),
            position_ned=(posv[0], posv[1], posv[2]),
            velocity_ned=(posv[3], posv[4], posv[5]),
            specific_force_body=(att[6], att[7], att[8]),
            on_ground=self.on_ground,
        )
