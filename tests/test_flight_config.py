"""The sequence's settings: one frozen options object whose comments say why, not what ran."""

from __future__ import annotations

import dataclasses
import io
import re
import tokenize
from pathlib import Path

import pytest

from mrft_gcs.flight import config, cycles, sequence, takeoff
from mrft_gcs.flight.config import SequenceConfig
from mrft_gcs.flight.phases import altitude, attitude, liftoff, shared, side, state
from mrft_gcs.sitl import available_vehicles


def test_settings_are_frozen_and_changed_only_by_replace():
    cfg = SequenceConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.period_tol = 0.1  # type: ignore[misc]
    other = dataclasses.replace(cfg, period_tol=0.1)
    assert other.period_tol == 0.1 and cfg.period_tol == 0.05
    assert hash(cfg) == hash(SequenceConfig())  # every field immutable, nested ones too
    assert sequence.SequenceConfig is SequenceConfig  # still importable from the sequence


@pytest.mark.parametrize("module", [config, cycles, sequence, takeoff, state, shared, liftoff,
                                    altitude, attitude, side], ids=lambda m: m.__name__)
def test_comments_name_no_airframe_seed_or_run(module):
    """Evidence (airframes, seeds, figures of past runs) lives in docs/, not in comments."""
    text = Path(module.__file__).read_text()
    words = [*available_vehicles(), "seed", "tune_stalls", "random vehicle"]
    found = []
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type in (tokenize.COMMENT, tokenize.STRING):
            found += [(tok.start[0], w) for w in words
                      if re.search(rf"\b{re.escape(w)}", tok.string, re.IGNORECASE)]
    assert found == []
