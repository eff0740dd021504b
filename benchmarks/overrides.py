"""``--set NAME=VALUE`` for the tune benchmarks: fly with some :class:`SequenceConfig` fields
changed, so that an A/B comparison README quotes can be repeated from the command line.

``NAME`` is a field of :class:`~mrft_gcs.flight.sequence.SequenceConfig`, or
``takeoff.FIELD`` for one of its :class:`~mrft_gcs.flight.takeoff.TakeoffSettings`;
``VALUE`` is a Python literal (a bare ``a,b`` is a tuple)::

    --set relax_after_cycles=None,None,None      # the cycle detector never relaxes
    --set takeoff.climb_pd=6,2.5 --set h_side_min=0.12

>>> from mrft_gcs.flight.sequence import SequenceConfig
>>> c = apply_overrides(SequenceConfig(), ["relax_after_cycles=None,None,None",
...                                        "takeoff.climb_pd=(6, 2.5)", "period_tol=0.03"])
>>> c.relax_after_cycles, c.takeoff.climb_pd, c.period_tol
((None, None, None), (6, 2.5), 0.03)
>>> apply_overrides(SequenceConfig(), ["no_such_field=1"])
Traceback (most recent call last):
...
ValueError: --set no_such_field=1: SequenceConfig has no field 'no_such_field'
>>> apply_overrides(SequenceConfig(), ["period_tol=five"])
Traceback (most recent call last):
...
ValueError: --set period_tol=five: 'five' is not a Python literal
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
from collections.abc import Iterable

__all__ = ["apply_overrides", "add_set_option", "checked_overrides"]


def _value(text: str, item: str) -> object:
    try:
        return ast.literal_eval(text)  # "6,2.5" parses as a tuple too
    except (ValueError, SyntaxError):
        raise ValueError(f"--set {item}: {text!r} is not a Python literal") from None


def _replace(obj: object, path: list[str], value: object, item: str) -> object:
    names = {f.name for f in dataclasses.fields(obj)}  # type: ignore[arg-type]
    if path[0] not in names:
        raise ValueError(f"--set {item}: {type(obj).__name__} has no field {path[0]!r}")
    if len(path) > 1:
        value = _replace(getattr(obj, path[0]), path[1:], value, item)
    return dataclasses.replace(obj, **{path[0]: value})  # type: ignore[type-var]


def apply_overrides(config, items: Iterable[str]):
    """``config`` with each ``NAME=VALUE`` of ``items`` applied (see the module doc)."""
    for item in items:
        name, sep, text = item.partition("=")
        if not sep:
            raise ValueError(f"--set {item}: expected NAME=VALUE")
        config = _replace(config, name.strip().split("."), _value(text.strip(), item), item)
    return config


def add_set_option(ap: argparse.ArgumentParser) -> None:
    """The benchmarks' ``--set`` option (repeatable)."""
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="tune with a SequenceConfig field changed (takeoff.FIELD for the "
                         "take-off settings; repeatable), e.g. relax_after_cycles=None,None,None")


def checked_overrides(ap: argparse.ArgumentParser, items: list[str]) -> tuple[str, ...]:
    """``items`` once they apply to the default SequenceConfig: a typo stops the benchmark
    with a one-line usage error before the first tune, not after it."""
    from mrft_gcs.flight.sequence import SequenceConfig

    try:
        apply_overrides(SequenceConfig(), items)
    except ValueError as err:
        ap.error(str(err))
    return tuple(items)
