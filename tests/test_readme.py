"""README as a manual: its commands match CI, its figures are what the report script
writes from the saved records, and its links and quoted paths resolve."""

from __future__ import annotations

import importlib.util
import json
import math
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
RESULTS = ROOT / "benchmarks" / "results"


def _report_module():
    spec = importlib.util.spec_from_file_location("bench_report", ROOT / "benchmarks" / "report.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_second_command_is_what_ci_runs() -> None:
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1].strip()
    assert f"    {ci}\n" in README.read_text()


def test_first_command_is_the_demo() -> None:
    cmd = "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/mrft-tune demo"
    assert f"    {cmd}\n" in README.read_text()


def test_readme_stays_a_manual() -> None:
    text = README.read_text()
    assert len(text.splitlines()) <= 400
    # the pointer to flying safely is within the first screenful
    head = "\n".join(text.splitlines()[:40])
    assert "Before you fly a real vehicle" in head and "A first real flight" in head
    # no commit hashes (README quotes figures, history lives in git)
    assert not re.search(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b", text)


@pytest.mark.parametrize("page", [README, *sorted((ROOT / "docs").glob("*.md"))],
                         ids=lambda p: p.name)
def test_links_and_quoted_paths_resolve(page: Path) -> None:
    text = page.read_text()
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if not target.startswith("http"):
            assert (page.parent / target).exists(), f"{page.name}: broken link {target}"
    for path in re.findall(r"`((?:mrft_gcs|benchmarks|profiles|tests|models|docs)/[^`\s*<]*)`",
                           text):
        assert (ROOT / path.split("::")[0]).exists(), f"{page.name}: no such path {path}"


def test_readme_figures_are_the_saved_records() -> None:
    rep = _report_module()
    runs_path, evals_path = RESULTS / "tune_runs.json", RESULTS / "evaluation.json"
    runs, evals = json.loads(runs_path.read_text()), json.loads(evals_path.read_text())
    where = rep.measured_on(runs_path)
    command = rep.regenerate_command(runs_path.relative_to(ROOT), evals_path.relative_to(ROOT))
    assert rep.markdown(runs, evals, where, command) in README.read_text()
    assert rep.detail_markdown(runs, evals, where, command) in rep.DETAIL_PAGE.read_text()
    assert "Firecracker" in where  # the machine comes from the records, not this one


def test_summary_counts_an_unstable_loop() -> None:
    rep = _report_module()
    loops = {lp: {"J_pct": 1.0, "pm_deg": 20.0} for lp in rep.LOOPS}
    loops["roll"] = {"J_pct": math.inf, "pm_deg": None}
    runs = [{"vehicle": "v", "status": "ok", "duration_s": 9.0, "loops": loops}]
    table = rep.summary_table(runs, [])
    assert "1.0 (1 unstable) / 20.0 (3 loops)" in table
    assert "v 1/1 (9.0 / 9.0 s)" in table
