"""The whole simulated vehicle in-process: physics plus onboard software, no sockets.

:class:`SimVehicle` is what the MAVLink server wraps, and what unit tests step directly::

    >>> from mrft_gcs.sitl import SimVehicle, load_airframe
    >>> v = SimVehicle(load_airframe("qdrone"), seed=0)
    >>> v.run(0.1)          # 100 steps of 1 ms, disarmed on the ground
    >>> v.physics.on_ground
    True
"""

from __future__ import annotations

from mrft_gcs.sitl.airframe import Airframe
from mrft_gcs.sitl.onboard import Autopilot
from mrft_gcs.sitl.physics import DT_S, Multirotor

__all__ = ["SimVehicle"]


class SimVehicle:
    """Physics (:class:`Multirotor`) driven by the onboard software (:class:`Autopilot`).

    Parameters
    ----------
    airframe : Airframe
    seed : int
        Sensor-noise seed; a run is deterministic given the seed and the timing of commands
        in simulated time.
    wind_m_s : (3,) float
        Constant wind, NED.
    dt_s : float
        Physics step (1 ms); the autopilot runs at ``airframe.onboard.loop_hz``.
    physics : Multirotor, optional
        Another physics with the same interface and step ``dt_s`` (e.g.
        :class:`mrft_gcs.sitl.rotorpy_physics.RotorpyMultirotor`); default the bundled one.
    """

    def __init__(self, airframe: Airframe, seed: int = 0,
                 wind_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 dt_s: float = DT_S, physics: Multirotor | None = None) -> None:
        self.airframe = airframe
        self.dt = dt_s
        self.physics = physics if physics is not None else Multirotor(
            airframe, dt_s=dt_s, seed=seed, wind_m_s=wind_m_s)
        spec = airframe.onboard
        #: the autopilot runs on every ``control_every``-th physics step, its command held
        self.control_every = max(1, int(round(1.0 / (spec.loop_hz * dt_s))))
        pos_every = max(1, int(round(spec.loop_hz / spec.position_loop_hz)))
        self.autopilot = Autopilot(dt_s * self.control_every,
                                   hover_thrust=airframe.hover_thrust
                                   * airframe.hover_estimate_factor,
                                   spec=spec, position_every=pos_every)
        self.steps = 0
        self._cmd = (0.0, 0.0, 0.0, 0.0)

    def reset(self, position_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
              airborne: bool = False) -> None:
        """Back to boot state (parameters kept); optionally start in the air at hover."""
        self.physics.reset(position_ned, airborne=airborne)
        params = self.autopilot.params
        self.autopilot.reset()
        self.autopilot.params = params
        self.steps = 0
        self._cmd = (0.0, 0.0, 0.0, 0.0)

    @property
    def time_s(self) -> float:
        return self.physics.t

    def step(self) -> None:
        """One physics step, after a control step where the autopilot's loop is due."""
        ph = self.physics
        if self.steps % self.control_every == 0:
            self._cmd = self.autopilot.update(ph.t, ph.meas_att, ph.meas_posv, ph.on_ground)
        ph.step(*self._cmd)
        self.steps += 1

    def run(self, duration_s: float) -> None:
        """Step for ``duration_s`` of simulated time."""
        for _ in range(int(round(duration_s / self.dt))):
            self.step()
