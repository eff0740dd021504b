"""What the CLI prints: brackets kept, real option types, full-width tables when piped."""

from __future__ import annotations

import re

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
