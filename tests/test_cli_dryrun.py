"""`mrft-tune dry-run` as a user sees it: exit codes, which gains are written, plots, --json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mrft_gcs.cli import main
from mrft_gcs.errors import IdentificationError

SHARED = Path(__file__).resolve().parents[2] / "shared" / "logs"
NO_RELAY = [SHARED / "px4-sample-flight.ulg", Path(__file__).parent / "data" / "sample.tlog"]


@pytest.fixture(autouse=True)
def _pinned_width(monkeypatch):
    monkeypatch.setenv("COLUMNS", "250")


@pytest.mark.parametrize("log", NO_RELAY, ids=lambda p: p.name)
def test_no_relay_test_exits_6_writes_the_report_and_no_plot(log, tmp_path, capsys):
    if not log.exists():
        pytest.skip(f"{log} not found")
    report, png = tmp_path / "r.json", tmp_path / "p.png"
    code = main(["dry-run", str(log), "--report", str(report), "--plot", str(png)])
    assert code == IdentificationError.exit_code == 6
    out, err = capsys.readouterr()
    assert "no relay test found" in out and "no plot written" in out
    assert not png.exists()
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "no relay test found" in errors[0]
    assert json.loads(report.read_text())["status"] == "no_identification"


def _table_row(text: str, title: str, first_cell: str) -> dict[str, str]:
    """The row starting with ``first_cell`` of the table titled ``title``, by column header."""
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.strip() == title)
    header = [c.strip() for c in lines[start + 2].split("┃")[1:-1]]
    for ln in lines[start + 4:]:
        cells = [c.strip() for c in ln.split("│")[1:-1]]
        if cells and cells[0] == first_cell:
            return dict(zip(header, cells, strict=True))
    raise AssertionError(f"no row {first_cell} in {title}:\n{text}")


def test_one_clearly_labelled_written_value(roll_relay_tlog, capsys):
    """The "written" gains are the ones behind the parameters; the identified ones (relay
    through the ground station) are labelled as such."""
    from mrft_gcs.dryrun import dry_run
    from mrft_gcs.profiles import load_profile

    res = dry_run(roll_relay_tlog, profile=load_profile("px4"))
    r = res.loops[0]
    assert r.gains != r.identification.gains  # re-targeted: two values exist to confuse
    assert main(["dry-run", str(roll_relay_tlog), "--profile", "px4"]) == 0
    out = capsys.readouterr().out
    row = _table_row(out, "identified loops", "roll")
    assert "Kc" not in row and "Kd" not in row  # no unlabelled gain column
    assert row["written Kc"] == f"{r.gains.Kc:.3g}" and row["written Kd"] == f"{r.gains.Kd:.3g}"
    assert row["identified Kc, Kd"] == (f"{r.identification.gains.Kc:.3g}, "
                                        f"{r.identification.gains.Kd:.3g}")
    assert "written: the gains a tune writes" in out
    # PX4: rate P = Kd, angle P = Kc / Kd of the written gains
    assert res.parameters["MC_ROLLRATE_P"] == pytest.approx(r.gains.Kd, rel=1e-9)
    assert res.parameters["MC_ROLL_P"] == pytest.approx(r.gains.Kc / r.gains.Kd, rel=1e-9)


def test_json_prints_the_report_alone_on_stdout(roll_relay_tlog, capsys):
    assert main(["dry-run", str(roll_relay_tlog), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["schema"].startswith("mrft-gcs/dry-run/")
    assert data["loops"]["roll"]["gains"]["Kc"] > 0


def test_plot_shows_relay_step_and_bode_with_labelled_axes(roll_relay_tlog, tmp_path):
    from mrft_gcs.dryrun import dry_run
    from mrft_gcs.plots.figures import dry_run_panels, panels_figure

    res = dry_run(roll_relay_tlog)
    fig = panels_figure(dry_run_panels(res), "dry-run")
    try:
        labels = {(ax.get_title(), ax.get_xlabel(), ax.get_ylabel()) for ax in fig.get_axes()}
        text = " | ".join(" ".join(x) for x in labels)
        for want in ("time (s)", "relay u: torque command (normalised)",
                     "measured roll angle (rad)", "angle per unit set point (rad/rad)",
                     "|L| (dB)", "phase of L (deg)", "frequency (rad/s)", "predicted unit step"):
            assert want in text, (want, text)
        legends = " ".join(t.get_text() for ax in fig.get_axes() if ax.get_legend()
                           for t in ax.get_legend().get_texts())
        assert "phase margin" in legends and "gain margin" in legends
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)
    png = tmp_path / "dry.png"
    assert main(["dry-run", str(roll_relay_tlog), "--plot", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG" and png.stat().st_size > 20_000
