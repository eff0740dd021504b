"""Runtime identification: from a steady relay cycle to a model and PD gains.

This is the one pipeline shared by live tuning (``mrft-tune tune``) and log
replay (``mrft-tune dry-run``). It uses only numpy and onnxruntime (never
torch) and the bundled classifiers in ``models/``.

Interface (stable; other modules build on it):

- :func:`relay_settings` -> :class:`RelaySettings`: the MRFT ``beta`` (the
  domain's distinguishing phase; for side motion it depends on the identified
  attitude loop) and a default relay amplitude ``h`` for a loop kind.
- :class:`CycleDetector`: streaming; ``reset()``, ``update(t_s, u, y)`` with one
  sample at a time, ``status()`` -> :class:`CycleStatus`; says when the
  oscillation is steady and hands back the samples of the last steady cycles.
- :func:`identify` -> :class:`Identification`: classify the cycle, recover the
  gain by exact gain scaling, return the model and the PD gains in SI units of
  the loop (``u = Kc e - Kd dy/dt``); :class:`Diagnostics` says which path
  (:class:`Method`) produced it, which bundled shape it belongs to, and holds the
  classifier's vote (:class:`ClassifierVote`) and the harmonic fit (:class:`HarmonicFit`).
- :func:`attach_residual`: the residual analysis for the report, after the tests
  (:class:`ResidualSummary`).

Modules: ``result`` (the typed results), ``detector`` (the cycle detector),
``runtime`` (the classifiers, exact gain scaling, the refinement on the measured
harmonics), ``harmonics`` (the harmonics of a relay cycle and the model fits on
them), ``closed_loop`` (the autopilot's closed attitude loop measured behind a side
relay), ``side`` (what side identification shares with the side classifiers'
design), ``residual``, ``live`` (the entry points a tune calls on a relay test's
record) and ``worker`` (those entry points in a process of their own).

Units per loop (the input ``u`` is what the relay drives, ``y`` what is measured):
roll/pitch: ``u`` normalised torque command in [-1, 1], ``y`` angle in rad;
altitude: ``u`` normalised collective thrust (deviation from hover), ``y``
altitude in m, up positive; x/y: ``u`` tilt angle set point of the closed
attitude loop in rad (x: -pitch, y: +roll, yaw 0, NED), ``y`` position in m.
"""

from __future__ import annotations

from mrft_gcs.identify.detector import CycleDetector, CycleStatus
from mrft_gcs.identify.residual import attach_residual
from mrft_gcs.identify.result import (
    ClassifierVote,
    Diagnostics,
    HarmonicFit,
    Identification,
    MeasuredLoop,
    Method,
    RelaySettings,
    ResidualSummary,
)
from mrft_gcs.identify.runtime import identify, relay_settings

__all__ = [
    "attach_residual",
    "ClassifierVote",
    "CycleDetector",
    "CycleStatus",
    "Diagnostics",
    "HarmonicFit",
    "Identification",
    "MeasuredLoop",
    "Method",
    "RelaySettings",
    "ResidualSummary",
    "identify",
    "relay_settings",
]
