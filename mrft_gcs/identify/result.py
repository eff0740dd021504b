"""Typed results of runtime identification: relay settings, the identification, its diagnostics."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from mrft_gcs.loops import LoopKind
from mrft_gcs.plant import PD, InnerModel, SideModel

__all__ = ["Diagnostics", "Identification", "MeasuredLoop", "Method", "RelaySettings"]


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
    """

    w: np.ndarray
    T: np.ndarray
    sd: np.ndarray
    rms_sd: float
    harmonics: tuple[int, ...]


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
    """

    method: Method = Method.GIVEN
    shape: int | None = None
    scale: float = float("nan")
    measured: MeasuredLoop | None = None


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
    extras : dict
        Free-form diagnostics for reports and debugging (gain estimate, top classes,
        fit cost, ``residual``...); nothing decides on them.
    diagnostics : Diagnostics
        What other code decides on: the method, the shape and scale.
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
    extras: dict = field(default_factory=dict)
    diagnostics: Diagnostics = field(default_factory=Diagnostics)
