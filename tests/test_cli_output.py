"""What the CLI prints: brackets kept, real option types, full-width tables when piped."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from mrft_gcs.cli import main


@pytest.fixture(autouse=True)
def _pinned_width(monkeypatch):
    # click lays out --help from COLUMNS; pin it so the tests see one layout
    monkeypatch.setenv("COLUMNS", "100")


def _option_line(text: str, option: str) -> str:
    options = text.split("Options:", 1)[1]
    lines = [ln for ln in options.splitlines() if re.match(rf"\s+(-\w, )?{option}\b", ln)]
    assert lines, f"{option} not in help:\n{text}"
    return lines[0]


def test_fleet_error_keeps_the_table_name_in_brackets(tmp_path, capsys):
    fleet = tmp_path / "fleet.toml"
    fleet.write_text('[defaults]\nprofile = "sitl"\n', encoding="utf-8")
    assert main(["fleet", str(fleet), "--yes"]) == 2
    err = capsys.readouterr().err
    assert "needs at least one [[vehicle]] table" in err, err
    assert len(err.strip().splitlines()) == 1


def test_design_help_names_the_extra_in_brackets(capsys):
    assert main(["design", "--help"]) == 0
    assert "pip install -e '.[design]'" in " ".join(capsys.readouterr().out.split())


def test_help_shows_value_types_and_no_type_for_flags(capsys):
    assert main(["tune", "--help"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"<str>|TEXT", _option_line(out, "--connect"))
    assert re.search(r"<float>|FLOAT", _option_line(out, "--altitude"))
    assert re.search(r"<path>|PATH|FILE", _option_line(out, "--report"))
    assert "<bool>" not in out
    # a flag takes no value: nothing between its name and its help
    assert re.search(r"--dry-link\s+connect and check", _option_line(out, "--dry-link"))


def _run_piped(*args: str, cwd) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    return subprocess.run([sys.executable, "-m", "mrft_gcs.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_piped_output_keeps_table_rows_and_notes_whole(roll_relay_tlog, tmp_path):
    from mrft_gcs.dryrun import dry_run

    res = dry_run(roll_relay_tlog)
    ident = res.loops[0].identification
    model = ", ".join(f"{k}={v:.3g}" for k, v in ident.model.as_dict().items())
    assert len(model) > 30
    proc = _run_piped("dry-run", str(roll_relay_tlog), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    rows = [ln for ln in proc.stdout.splitlines() if ln.startswith("│ roll")]
    assert rows and model in rows[0], proc.stdout
    assert max(len(ln) for ln in proc.stdout.splitlines()) > 100
    for line in res.explanation().splitlines():
        assert line in proc.stdout.splitlines(), line


def test_verify_defaults_to_the_profile_tune_defaults_to(capsys):
    import typer.main

    from mrft_gcs.cli import _register, app

    _register()
    group = typer.main.get_command(app)
    defaults = {name: next(p.default for p in group.commands[name].params if p.name == "profile")
                for name in ("tune", "verify")}
    assert defaults["tune"] == defaults["verify"] == "px4"
    for name in ("tune", "verify"):
        assert main([name, "--help"]) == 0
        options = capsys.readouterr().out.split("Options:", 1)[1]
        entry = re.split(r"\n  -", options.split("--profile", 1)[1], maxsplit=1)[0]
        assert "[default: px4]" in " ".join(entry.split()), entry


def _all_help(capsys) -> str:
    texts = []
    for args in (["--help"], ["tune", "--help"], ["params", "--help"], ["fleet", "--help"],
                 ["verify", "--help"], ["dry-run", "--help"], ["demo", "--help"],
                 ["sitl", "--help"]):
        assert main(args) == 0
        texts.append(capsys.readouterr().out)
    for sub in ("restore", "backup", "show"):
        assert main(["params", sub, "--help"]) == 0
        texts.append(capsys.readouterr().out)
    return "\n".join(texts)


def test_example_serial_rates_carry_a_relay_test(capsys):
    """Every baud rate the tool shows as an example is one it accepts for a relay test."""
    import mrft_gcs.fleet
    from mrft_gcs.link.connection import ACCEPTED_FORMS
    from mrft_gcs.link.quality import check_serial_baud

    text = "\n".join([_all_help(capsys), ACCEPTED_FORMS, mrft_gcs.fleet.__doc__ or ""])
    rates = [int(r) for r in re.findall(r"(?:tty\w*,|baud\s*=\s*|--baud\s+)(\d{4,})", text)]
    assert len(rates) >= 2, text  # the connection forms and the fleet file show one each
    for rate in rates:
        check_serial_baud(rate)  # raises LinkError for a rate too slow for a relay test
