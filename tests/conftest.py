"""Fixtures more than one test module uses."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def roll_relay_tlog(tmp_path_factory):
    """A .tlog of a roll relay test on the simulated vehicle (the bundled classifier's beta)."""
    from mrft_gcs.identify import relay_settings
    from mrft_gcs.loops import LoopKind
    from mrft_gcs.residual.synth import sitl_relay_record, write_relay_tlog

    rec = sitl_relay_record("roll", seed=4, beta=relay_settings(LoopKind.ATTITUDE).beta, h=0.08,
                            duration_s=6.0)
    path = tmp_path_factory.mktemp("relay") / "relay.tlog"
    write_relay_tlog(path, "roll", rec.t, rec.u, rec.y)
    return path

