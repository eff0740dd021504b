"""Typed results of runtime identification: relay settings, the identification, its diagnostics.

Every field is typed (no free-form dict): :class:`Diagnostics` holds what the path that
ran decided (:class:`Method`, the shape, the classifier's vote, the harmonic fit), and
:class:`ResidualSummary` the residual analysis the report shows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from mrft_gcs.loops import LoopKind
from mrft_gcs.plant import PD, InnerModel, SideModel

__all__ = ["ClassifierVote", "Diagnostics", "HarmonicFit", "Identification", "MeasuredLoop",
           "Method", "RelaySettings", "ResidualSummary"]


@dataclass(frozen=True)
class RelaySettings:
    """MRFT settings for one loop: ``beta`` and the default amplitude ``h`` (input units)."""

    beta: float
    h: float


class Method(StrEnum):
    """Which path produced an identification (its value is the report's wording)."""

    #: the classifier's Bayes rule alone (one cycle, or a refinement that was not trusted)
    CLASSIFIER = "classifier"
    #: the classifier, then the model refined on the relay cycle's measured harmonics
    CLASSIFIER_HARMONICS = "classifier + harmonics"
    #: side motion: the model fitted on the measured harmonics behind the attitude loop
    HARMONIC_FIT = "harmonic fit"
    #: the autopilot's closed attitude loop measured behind a side relay (attitude path)
    CLOSED_LOOP = "closed attitude loop"
    #: built by hand (a test, a known model), not identified from a relay test
    GIVEN = "given"


@dataclass(frozen=True)
class MeasuredLoop:
    """A closed loop measured at the relay's odd harmonics.

    Attributes
    ----------
    w : array (n,)
        Frequencies of the points the fit kept, rad/s.
    T : complex array (n,)
        The measured closed-loop response there (set point to output).
    sd : array (n,)
        Standard error of each point (log units, model error included).
    rms_sd : float
        RMS residual of the equivalent loop's fit, in standard errors.
    harmonics : tuple of int
        The harmonic number of each point.
    max_dev : (float, float)
        Largest deviation of the fitted loop from the measured points: relative gain
        (fraction) and phase (deg).
    """

    w: np.ndarray
    T: np.ndarray
    sd: np.ndarray
    rms_sd: float
    harmonics: tuple[int, ...]
    max_dev: tuple[float, float] = (float("nan"), float("nan"))


@dataclass(frozen=True)
class ClassifierVote:
    """What a classifier decided (inner loops; side motion when its harmonic fit was refused).

    Attributes
    ----------
    rule : int
        The shape whose tuning rule gave the gains (the Bayes decision on the
        probabilities). Inner loops: the same as :attr:`Diagnostics.shape`; side motion:
        a side shape of the attitude shape's side classifier.
    top : tuple of int
        The three likeliest shapes, most likely first (inner loops: after the measured
        harmonics' likelihood where there were several cycles).
    duty : float
        The relay cycle's duty cycle (fraction of the period on the high level).
    bias : float
        The relay output's bias seen over the cycle (input units).
    likeliest : int or None
        Inner loops: the classifier's own likeliest shape (before the harmonics).
    probs : tuple of float
        Inner loops: the classifier's three largest probabilities, largest first.
    margin_guard_scale : float
        Side motion: the factor the measured-margin guards scaled the rule's gains by
        (1: untouched); NaN for inner loops.
    """

    rule: int
    top: tuple[int, ...]
    duty: float
    bias: float
    likeliest: int | None = None
    probs: tuple[float, ...] = ()
    margin_guard_scale: float = float("nan")


@dataclass(frozen=True)
class HarmonicFit:
    """The model fitted on (inner loops: refined on) the relay cycle's measured harmonics.

    Attributes
    ----------
    cost : float
        The fit's cost (squared standardised residuals, prior included); infinite when
        an inner loop's refinement was not trusted and the rule's gains stand.
    held_back : float
        Inner loops: how far the gains went from the rule's (0) towards the refined
        model's optimal PD (1), log-linearly; NaN for side motion.
    harmonics : tuple of int
        Side motion: the harmonic numbers the fit used.
    sd : tuple of float
        Side motion: the standard error of each measured harmonic (log units).
    t_att_measured : tuple of int
        Side motion: the harmonics at which the closed attitude loop was measured
        during the test rather than modelled.
    df_factor : float
        Side motion: the measured fundamental's gain over the describing function's
        estimate ``4 h / (pi a)`` (to evaluate a describing-function gain instead).
    pm_deg : float
        Side motion: the design's phase margin on the fitted model, deg.
    """

    cost: float
    held_back: float = float("nan")
    harmonics: tuple[int, ...] = ()
    sd: tuple[float, ...] = ()
    t_att_measured: tuple[int, ...] = ()
    df_factor: float = float("nan")
    pm_deg: float = float("nan")


@dataclass(frozen=True)
class Diagnostics:
    """What identification decided that other code builds on.

    Attributes
    ----------
    method : Method
        The path that produced the identification.
    shape : int or None
        Inner loops: the bundled shape whose tuning rule gave the gains; the closed
        attitude loop: the bundled attitude shape nearest to the measurement. It picks
        the side classifier behind this loop. None for side motion.
    scale : float
        That shape's time scale ``c`` (the shape's unit time constants times ``c``);
        NaN with no shape.
    measured : MeasuredLoop or None
        The closed attitude loop's measured points (:attr:`Method.CLOSED_LOOP` only).
    classifier : ClassifierVote or None
        The classifier's vote, where a classifier ran.
    fit : HarmonicFit or None
        The fit on the measured harmonics, where one ran (inner loops: two or more
        cycles; side motion: :attr:`Method.HARMONIC_FIT`).
    fit_note : str
        Side motion decided by the classifier: why the harmonic fit was not used.
    """

    method: Method = Method.GIVEN
    shape: int | None = None
    scale: float = float("nan")
    measured: MeasuredLoop | None = None
    classifier: ClassifierVote | None = None
    fit: HarmonicFit | None = None
    fit_note: str = ""


@dataclass(frozen=True)
class ResidualSummary:
    """The residual analysis of an identification (README's report schema ``residual``).

    Attributes
    ----------
    rms_before, rms_after : float
        Normalised RMS of the measured cycle minus the model's, without and with the
        named effect; NaN where not analysed.
    effect : str or None
        The effect that explains the residual, if any.
    effect_params : dict of str to float
        The effect's fitted parameters.
    note : str
        Why the analysis is missing, where it is.
    """

    rms_before: float = float("nan")
    rms_after: float = float("nan")
    effect: str | None = None
    effect_params: dict[str, float] = field(default_factory=dict)
    note: str = ""


@dataclass(frozen=True)
class Identification:
    """Result of identifying one loop from its steady relay cycle.

    Attributes
    ----------
    kind : LoopKind
        Model family (attitude, altitude, side).
    model : InnerModel or SideModel
        Identified model in SI units of the loop.
    class_index : int
        Index of the representative process chosen by the classifier.
    confidence : float
        Classifier probability mass behind the chosen gains, in [0, 1].
    beta, h : float
        Relay settings of the test.
    period_s, amplitude : float
        Of the measured steady cycle.
    gains : PD
        PD gains in SI units (``u = Kc e - Kd dy/dt``).
    diagnostics : Diagnostics
        How it was identified: the method, the shape and scale, the classifier's vote,
        the harmonic fit.
    residual : ResidualSummary or None
        The residual analysis, once attached
        (:func:`~mrft_gcs.identify.residual.attach_residual`).
    inner : Identification or None
        Side motion: the attitude identification the side loop was identified behind.
    """

    kind: LoopKind
    model: InnerModel | SideModel
    class_index: int
    confidence: float
    beta: float
    h: float
    period_s: float
    amplitude: float
    gains: PD
    diagnostics: Diagnostics = field(default_factory=Diagnostics)
    residual: ResidualSummary | None = None
    inner: Identification | None = None
