"""The parameter round trip every real-firmware test checks: backed up, written, read back,
restored (SPEC's "loses nothing")."""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import pytest

from mrft_gcs.params import ParamClient


def assert_round_trip(client: ParamClient, names: Sequence[str], tmp_path: Path) -> None:
    """Write 0.9 x each of ``names``: the backup holds the old values, the vehicle reads back
    the new ones, and a restore from the backup puts the old ones back."""
    before = {n: p.value for n, p in client.read_many(names).items()}
    wanted = {n: round(v * 0.9, 3) for n, v in before.items()}
    t = time.monotonic()
    result = client.write(wanted, tmp_path)
    print(f"{len(names)} parameters backed up, written, read back in "
          f"{time.monotonic() - t:.2f} s")
    assert result.backup_path.is_file()
    for change in result.changes:
        assert change.old == pytest.approx(before[change.name], rel=1e-6)
        assert change.new == pytest.approx(wanted[change.name], rel=1e-6)
    assert {n: p.value for n, p in client.read_many(names).items()} == pytest.approx(wanted)
    client.restore(result.backup_path, tmp_path)
    assert {n: p.value for n, p in client.read_many(names).items()} == pytest.approx(before)
