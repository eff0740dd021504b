"""Test helper: the ``mrft-tune sitl`` command as a real process."""

from __future__ import annotations

import os
import subprocess
import sys
import time


def start_sitl_cli(*args: str) -> tuple[subprocess.Popen, str]:
    """``mrft-tune sitl ARGS`` as a real process, and what it printed up to its connection
    line (at most 20 s)."""
    proc = subprocess.Popen([sys.executable, "-m", "mrft_gcs.cli", "sitl", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "COLUMNS": "200"})
    lines = []
    end = time.monotonic() + 20
    while time.monotonic() < end:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        lines.append(line)
        if "connect with" in line:
            break
    return proc, "".join(lines)
