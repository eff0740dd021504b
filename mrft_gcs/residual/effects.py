"""Library of candidate unmodelled effects for residual analysis.

Each effect is a small frozen dataclass: its ``name`` (as in reports), the one
parameter it is fitted by (``param``, ``units``), how to bound that parameter
for a given relay test (:meth:`Effect.bounds`), how to switch it on in a batch
simulation (:meth:`Effect.apply`, which writes into :class:`Knobs`), and how a
fitted value changes the linear model used for PD design (:meth:`Effect.design_factor`).

All effects act in the *loop's* units (see :mod:`mrft_gcs.identify`): ``u`` is
the relay output as commanded, ``y`` the measured variable.

Under a relay every static input nonlinearity (saturation, dead zone, thrust
curve, bias) turns the two relay levels into two other levels, so from one
relay amplitude such effects are only told apart by how they move the two
levels (both shrink, one shrinks, both shift). The report lists the effects
that explain the data equally well (``alternatives``). Effects that change the
dynamics instead (delay, sensor filter, rate limit, drag) are told apart by the
response to each switch (:mod:`~mrft_gcs.residual.openloop`); ``Effect.static_map``
says which family an effect is in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mrft_gcs.loops import LoopKind

__all__ = [
    "Knobs",
    "RelayContext",
    "Effect",
    "InputBias",
    "ExtraDelay",
    "SensorLPF",
    "ActuatorSaturation",
    "ActuatorRateLimit",
    "QuadraticDrag",
    "MotorDeadzone",
    "ThrustCurve",
    "EFFECTS",
    "candidate_effects",
    "effect_by_name",
]


@dataclass
class Knobs:
    """Effect settings of a batch of ``n`` simulated candidates; neutral values switch off.

    Attributes (arrays of shape ``(n,)``)
    --------------------------------------
    bias : added to the commanded input (input units).
    delay_s : transport delay added to the model's (s).
    lpf_tau_s : time constant of a first-order low-pass on the measurement (s); 0 = off.
    u_max, u_min : clip of the input (input units); +-inf = off.
    rate : largest input slew (input units per s); inf = off.
    deadzone : dead band on the input (input units); 0 = off.
    curve_a, curve_hover : thrust curve ``(1-a) c + a c^2`` about the hover fraction; a = 0 off.
    drag : quadratic drag on the output rate, ``dv/dt -= drag |v| v`` (1 / output unit).
    """

    bias: np.ndarray
    delay_s: np.ndarray
    lpf_tau_s: np.ndarray
    u_max: np.ndarray
    u_min: np.ndarray
    rate: np.ndarray
    deadzone: np.ndarray
    curve_a: np.ndarray
    curve_hover: np.ndarray
    drag: np.ndarray

    @classmethod
    def neutral(cls, n: int, hover: float = 0.5) -> Knobs:
        """Every effect off for ``n`` candidates (``hover``: hover thrust fraction)."""
        z = np.zeros(n)
        return cls(bias=z.copy(), delay_s=z.copy(), lpf_tau_s=z.copy(),
                   u_max=np.full(n, np.inf), u_min=np.full(n, -np.inf), rate=np.full(n, np.inf),
                   deadzone=z.copy(), curve_a=z.copy(), curve_hover=np.full(n, float(hover)),
                   drag=z.copy())

    @property
    def n(self) -> int:
        return self.bias.size


@dataclass(frozen=True)
class RelayContext:
    """What bounds an effect's parameter: the relay that ran and the cycle it produced.

    Attributes
    ----------
    h, bias : float
        Relay amplitude and bias (input units).
    period_s, amplitude : float
        Of the measured steady cycle (s, output units).
    dt : float
        Relay sample time (s).
    hover : float
        Hover thrust as a fraction of full thrust (altitude thrust curve); 0.5 if unknown.
    """

    h: float
    bias: float
    period_s: float
    amplitude: float
    dt: float
    hover: float = 0.5


@dataclass(frozen=True)
class Effect:
    """Base of the candidate effects (see module docstring).

    Attributes
    ----------
    name : str
        Name used in reports (``residual.effect``).
    param, units : str
        The fitted parameter and its units.
    log_grid : bool
        Search the parameter on a logarithmic grid.
    loops : tuple of LoopKind
        Loop families where the effect is physically possible.
    static_map : bool
        A static map of the input: under a two-level relay it only moves the two
        levels (bias, saturation, dead zone, thrust curve), so it leaves no trace in
        the shape of the response to a switch.
    """

    name: str = ""
    param: str = ""
    units: str = ""
    log_grid: bool = False
    static_map: bool = False
    loops: tuple[LoopKind, ...] = field(default=(LoopKind.ATTITUDE, LoopKind.ALTITUDE))

    def bounds(self, ctx: RelayContext) -> tuple[float, float]:
        """Search interval of the parameter for this relay test."""
        raise NotImplementedError

    def apply(self, knobs: Knobs, idx: np.ndarray, values: np.ndarray) -> None:
        """Switch the effect on for candidates ``idx`` with parameter ``values``."""
        raise NotImplementedError

    def design_factor(self, value: float, ctx: RelayContext, w: np.ndarray) -> np.ndarray:
        """Factor multiplying ``G(jw)`` for PD re-design with the effect (1: gains unchanged)."""
        return np.ones_like(w, dtype=complex)

    def design_note(self, value: float, ctx: RelayContext) -> str:
        """One line: what re-design does with this effect."""
        return "gains unchanged: the effect does not alter the small-signal dynamics"

    def grid(self, ctx: RelayContext, n: int) -> np.ndarray:
        lo, hi = self.bounds(ctx)
        return np.geomspace(lo, hi, n) if self.log_grid else np.linspace(lo, hi, n)


@dataclass(frozen=True)
class InputBias(Effect):
    """A constant added to the input the loop receives (trim error, centre-of-mass offset)."""

    name: str = "input_bias"
    param: str = "bias"
    units: str = "input units"
    static_map: bool = True

    def bounds(self, ctx: RelayContext) -> tuple[float, float]:
        return -0.8 * ctx.h, 0.8 * ctx.h

    def apply(self, knobs, idx, values):
        knobs.bias[idx] += values

    def design_note(self, value, ctx):
        return f"gains unchanged; trim the input by {-value:+.4g} (or keep an integrator)"


@dataclass(frozen=True)
class ExtraDelay(Effect):
    """Transport delay the model lacks (link, estimator, filtering elsewhere)."""

    name: str = "extra_delay"
    param: str = "delay_s"
    units: str = "s"
    loops: tuple[LoopKind, ...] = (LoopKind.ATTITUDE, LoopKind.ALTITUDE, LoopKind.SIDE)

    def bounds(self, ctx):
        return 0.0, 0.3 * ctx.period_s

    def apply(self, knobs, idx, values):
        knobs.delay_s[idx] += values

    def design_factor(self, value, ctx, w):
        return np.exp(-1j * w * value)

    def design_note(self, value, ctx):
        return f"re-designed with tau + {value * 1e3:.1f} ms"


@dataclass(frozen=True)
class SensorLPF(Effect):
    """First-order low-pass filter on the measurement; the parameter is its cutoff."""

    name: str = "sensor_lpf"
    param: str = "cutoff_hz"
    units: str = "Hz"
    log_grid: bool = True

    def bounds(self, ctx):
        f0 = 1.0 / ctx.period_s
        return 0.6 * f0, min(30.0 * f0, 0.45 / ctx.dt)

    def apply(self, knobs, idx, values):
        knobs.lpf_tau_s[idx] = 1.0 / (2 * np.pi * values)

    def design_factor(self, value, ctx, w):
        return 1.0 / (1.0 + 1j * w / (2 * np.pi * value))

    def design_note(self, value, ctx):
        return f"re-designed with a {value:.3g} Hz first-order lag on the measurement"


@dataclass(frozen=True)
class ActuatorSaturation(Effect):
    """Input limited to ``u_max`` (and to ``-u_max`` when ``symmetric``).

    Torque commands saturate on both sides (symmetric); collective thrust
    saturates at full thrust only.
    """

    name: str = "actuator_saturation"
    param: str = "u_max"
    units: str = "input units"
    static_map: bool = True
    symmetric: bool = True

    def bounds(self, ctx):
        top = abs(ctx.bias) + ctx.h
        return 0.15 * top, 0.999 * top

    def apply(self, knobs, idx, values):
        knobs.u_max[idx] = values
        if self.symmetric:
            knobs.u_min[idx] = -values

    def design_note(self, value, ctx):
        return (f"gains unchanged (linear below the limit); the input saturates at "
                f"{value:.3g}: keep commands below it")


@dataclass(frozen=True)
class ActuatorRateLimit(Effect):
    """Largest slew of the input (input units per second)."""

    name: str = "actuator_rate_limit"
    param: str = "rate"
    units: str = "input units/s"
    log_grid: bool = True

    def bounds(self, ctx):
        return 2 * ctx.h / (0.5 * ctx.period_s), 2 * ctx.h / (0.5 * ctx.dt)

    def apply(self, knobs, idx, values):
        knobs.rate[idx] = values

    def design_factor(self, value, ctx, w):
        # Describing function at the test amplitude: a ramp of 2h/rate lags by h/rate.
        return np.exp(-1j * w * ctx.h / value)

    def design_note(self, value, ctx):
        return (f"re-designed with the ramp's equivalent delay h/rate = "
                f"{ctx.h / value * 1e3:.1f} ms (at the test amplitude)")


@dataclass(frozen=True)
class QuadraticDrag(Effect):
    """Quadratic drag on the output rate: ``dv/dt -= c |v| v`` (c = drag coefficient / mass)."""

    name: str = "quadratic_drag"
    param: str = "c_per_mass"
    units: str = "1/m"
    log_grid: bool = True
    loops: tuple[LoopKind, ...] = (LoopKind.ALTITUDE,)

    def bounds(self, ctx):
        v = 2 * np.pi * ctx.amplitude / ctx.period_s  # rate amplitude of the cycle
        # From 2 % to 10 x the linear damping 1/T at that rate (T ~ period / 3).
        return 0.02 * 3 / (ctx.period_s * v), 10 * 3 / (ctx.period_s * v)

    def apply(self, knobs, idx, values):
        knobs.drag[idx] = values

    def linear_damping(self, value: float, ctx: RelayContext) -> float:
        """Describing-function damping ``8 c V / (3 pi)`` at the test's rate amplitude V (1/s)."""
        v = 2 * np.pi * ctx.amplitude / ctx.period_s
        return 8 * value * v / (3 * np.pi)

    def design_note(self, value, ctx):
        return (f"re-designed with the drag linearised at the test's rate amplitude "
                f"(extra damping {self.linear_damping(value, ctx):.3g} 1/s)")


@dataclass(frozen=True)
class MotorDeadzone(Effect):
    """Dead band on the (torque) command: ``u -> sign(u) max(|u| - d, 0)``."""

    name: str = "motor_deadzone"
    param: str = "deadband"
    units: str = "input units"
    static_map: bool = True
    loops: tuple[LoopKind, ...] = (LoopKind.ATTITUDE,)

    def bounds(self, ctx):
        return 0.0, 0.85 * max(ctx.h - abs(ctx.bias), 1e-9)

    def apply(self, knobs, idx, values):
        knobs.deadzone[idx] = values

    def design_note(self, value, ctx):
        return (f"gains unchanged; small commands (< {value:.3g}) do nothing: expect a "
                f"limit cycle of that size")


@dataclass(frozen=True)
class ThrustCurve(Effect):
    """Motor thrust ``(1 - a) c + a c^2`` of the command ``c`` instead of ``c``.

    The loop input is the collective command's deviation from the hover command.
    """

    name: str = "thrust_curve"
    param: str = "a"
    units: str = "1"
    static_map: bool = True
    loops: tuple[LoopKind, ...] = (LoopKind.ALTITUDE,)

    def bounds(self, ctx):
        return 0.0, 1.0

    def apply(self, knobs, idx, values):
        knobs.curve_a[idx] = values

    def small_signal_gain(self, value: float, hover: float) -> float:
        if value <= 0:
            return 1.0
        c = (-(1 - value) + np.sqrt((1 - value) ** 2 + 4 * value * hover)) / (2 * value)
        return float(1 - value + 2 * value * c)

    def design_factor(self, value, ctx, w):
        return np.full_like(w, self.small_signal_gain(value, ctx.hover), dtype=complex)

    def design_note(self, value, ctx):
        return (f"re-designed with the small-signal thrust gain "
                f"{self.small_signal_gain(value, ctx.hover):.3g} x at hover")


#: Every candidate effect, in report order.
EFFECTS: tuple[Effect, ...] = (
    InputBias(),
    ExtraDelay(),
    SensorLPF(),
    ActuatorSaturation(),
    ActuatorRateLimit(),
    QuadraticDrag(),
    MotorDeadzone(),
    ThrustCurve(),
)


def candidate_effects(kind: LoopKind) -> tuple[Effect, ...]:
    """The effects that are physically possible on a loop family.

    Collective thrust saturates only at the top (``symmetric=False``); quadratic
    drag and the thrust curve act on altitude, the dead zone on torque commands.
    """
    out: list[Effect] = []
    for e in EFFECTS:
        if kind not in e.loops:
            continue
        if isinstance(e, ActuatorSaturation) and kind is LoopKind.ALTITUDE:
            e = ActuatorSaturation(symmetric=False)
        out.append(e)
    return tuple(out)


def effect_by_name(name: str) -> Effect:
    """The library effect called ``name``; ``KeyError`` lists the known names."""
    for e in EFFECTS:
        if e.name == name:
            return e
    raise KeyError(f"unknown effect {name!r}; known: {', '.join(e.name for e in EFFECTS)}")
