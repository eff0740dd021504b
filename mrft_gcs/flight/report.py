"""The tuning report (schema: README), rendered from a :class:`~mrft_gcs.flight.api.TuneResult`.

Schema ``mrft-gcs/tune-report/1`` (documented in README, section "Report schema").
Numbers that do not exist (a loop left alone, a tune that stopped early) are
``null``, never NaN, so every JSON reader takes the file.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from mrft_gcs.flight.api import SCHEMA, LoopResult, TuneResult
from mrft_gcs.flight.phases.yaw import YawOutcome
from mrft_gcs.params import ParamChange

__all__ = ["report_dict", "write_report", "SCHEMA"]


def _num(x: Any) -> Any:
    if x is None:
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _residual(lr: LoopResult) -> dict[str, Any]:
    res = lr.identification.residual if lr.identification else None
    if res is None:
        return {"rms_before": None, "rms_after": None, "effect": None, "effect_params": {}}
    return {"rms_before": _num(res.rms_before), "rms_after": _num(res.rms_after),
            "effect": res.effect,
            "effect_params": {str(k): _num(v) for k, v in res.effect_params.items()}}


def _loop(lr: LoopResult) -> dict[str, Any]:
    ident = lr.identification
    model = {k: _num(v) for k, v in ident.model.as_dict().items()} if ident else None
    return {
        "state": lr.state,
        "model": model,
        "class": int(ident.class_index) if ident else None,
        "confidence": _num(ident.confidence) if ident else None,
        "beta": _num(lr.beta),
        "h": _num(lr.h),
        "bias": _num(lr.bias),
        "band": _num(lr.band),
        "period_s": _num(lr.period_s),
        "amplitude": _num(lr.amplitude),
        "gains": {"Kc": _num(lr.gains.Kc), "Kd": _num(lr.gains.Kd)} if lr.gains else None,
        "tuned_after_s": _num(lr.t_tuned_s),
        "residual": _residual(lr),
        "verification": lr.verification.as_dict() if lr.verification else None,
        "note": lr.note or None,
    }


def _yaw(y: YawOutcome) -> dict[str, Any]:
    """``loops.yaw``: the keys of every loop (``state`` ``tuned`` or ``held``), then yaw's
    own: ``reason`` (why held; null where tuned), ``written`` (parameter -> value),
    ``pm_predicted_deg`` and ``crossover_rad_s`` on ArduCopter's yaw cascade, and
    ``steady_after_s`` (from the take-off command), ``max_error_deg`` and
    ``zero_moved_deg`` of its relay."""
    ident = y.identification
    return {
        "state": y.state,
        "model": {k: _num(v) for k, v in ident.model.as_dict().items()} if ident else None,
        "class": int(ident.class_index) if ident else None,
        "confidence": _num(ident.confidence) if ident else None,
        "beta": _num(y.beta), "h": _num(y.h), "bias": _num(y.bias), "band": _num(y.band),
        "period_s": _num(y.period_s), "amplitude": _num(y.amplitude),
        "gains": {"Kc": _num(y.gains.Kc), "Kd": _num(y.gains.Kd)} if y.gains else None,
        "tuned_after_s": _num(y.steady_after_s) if y.state == "tuned" else None,
        "residual": {"rms_before": None, "rms_after": None, "effect": None,
                     "effect_params": {}},
        # yaw's written gains are checked by the hover after the hand-over only
        "verification": None,
        "note": y.note or None,
        "reason": y.reason,
        "written": {k: _num(v) for k, v in y.written.items()},
        "pm_predicted_deg": _num(y.pm_predicted_deg),
        "crossover_rad_s": _num(y.crossover_rad_s),
        "steady_after_s": _num(y.steady_after_s),
        "max_error_deg": _num(math.degrees(y.max_error_rad)),
        "zero_moved_deg": _num(math.degrees(y.zero_moved_rad)),
    }


def report_dict(result: TuneResult) -> dict[str, Any]:
    """The report as plain JSON types (keys in README's report schema order, extras after)."""
    st = result.stream
    lq = result.link
    lim = result.limits
    return {
        "schema": SCHEMA,
        "vehicle": {"connection": result.connection, "autopilot": result.autopilot,
                    "profile": result.profile, "actuation": result.actuation,
                    "firmware": result.firmware.as_dict() if result.firmware else None},
        "started": result.started,
        "duration_s": _num(result.duration_s),
        "loops": {lp.value: _loop(lr) for lp, lr in result.loops.items()}
        | ({"yaw": _yaw(result.yaw)} if result.yaw is not None else {}),
        # new: what the tune wrote (read back); on_vehicle: what the vehicle holds at the end
        # (the old value again where the hold comparison reverted the set)
        "parameters": [{"name": c.name, "old": _num(c.old), "new": _num(c.new),
                        "on_vehicle": _num(_on_vehicle(result, c))}
                       for c in result.parameters],
        "backup": result.backup,
        "status": result.status,
        "error": result.error,
        "tlog": result.tlog,
        "max_tilt_deg": _num(result.max_tilt_deg),
        "hover_error_m": _num(result.hover_error_m),
        "hover_check": None if result.hover_check is None else {
            k: (_num(v) if isinstance(v, float) else v)
            for k, v in result.hover_check.as_dict().items()},
        # the written set held against the one it replaced (None: not flown)
        "hold_compare": None if result.hold_compare is None else result.hold_compare.as_dict(),
        # the onboard position loop's rate the altitude and x/y gains were designed for
        # (read: False where the vehicle did not say and the slowest rate was assumed)
        "position_loop": None if result.position_loop is None else {
            k: (_num(v) if isinstance(v, float) else v)
            for k, v in result.position_loop.as_dict().items()},
        "limits": None if lim is None else {k: _num(v) for k, v in vars(lim).items()},
        "stream": None if st is None else {
            "rate_hz_target": _num(st.rate_hz_target), "rate_hz": _num(st.rate_hz_achieved),
            "sent": st.sent, "skipped": st.skipped, "period_p50_ms": _num(st.period_p50_ms),
            "period_p99_ms": _num(st.period_p99_ms), "jitter_p99_ms": _num(st.jitter_p99_ms)},
        "link": None if lq is None else {
            "attitude_hz": _num(lq.attitude_hz), "position_hz": _num(lq.position_hz),
            "rtt_p50_ms": _num(lq.rtt_p50_ms), "rtt_max_ms": _num(lq.rtt_max_ms),
            "rtt_p90_ms": _num(lq.rtt_p90_ms), "rtt_method": lq.rtt_method},
        "notes": list(result.notes),
    }


def _on_vehicle(result: TuneResult, change: ParamChange) -> float:
    """The value of ``change``'s parameter on the vehicle when the tune ended: the hold
    comparison's last read-back where it swapped the parameter, else the written one."""
    hc = result.hold_compare
    if hc is not None and change.name in hc.on_vehicle:
        return hc.on_vehicle[change.name]
    return change.new


def write_report(result: TuneResult, path: str | os.PathLike[str]) -> Path:
    """Write the report JSON to ``path`` (folders created); returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(report_dict(result), indent=2) + "\n", encoding="utf-8")
    return p
