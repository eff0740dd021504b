"""The documented CSV format: explicit per-loop relay data.

For data that did not come from a MAVLink, PX4 or ArduPilot log (a bench rig,
another simulator, a spreadsheet), ``dry-run`` reads a plain CSV of the relay
input and the measured output of each loop.

Format (version 1)
------------------
- UTF-8 text (a byte-order mark is allowed), lines ending in ``\\n`` or ``\\r\\n``.
- Blank lines are ignored. Lines whose first non-blank character is ``#`` are
  comments. In a comment, whitespace-separated ``key=value`` tokens are metadata
  (e.g. ``# beta=-0.3 h=0.05 vehicle=quad-250``); a later value replaces an
  earlier one. Metadata is read by :func:`read_csv_metadata`.
- The first other line is the header: comma-separated column names, trimmed and
  case-insensitive. It must name ``t``, ``loop``, ``u`` and ``y`` (in any order);
  other columns are allowed and ignored.
- Every following line is one sample with as many comma-separated fields as the
  header (no quoting):

  ======  ==================================================================
  ``t``   time in seconds on any clock, the same for all rows
  loop    ``roll``, ``pitch``, ``altitude``, ``x`` or ``y`` (case-insensitive)
  ``u``   loop input, the relay output as applied, in the loop's input units:
          normalised torque in [-1, 1] for roll and pitch, normalised collective
          thrust in [0, 1] for altitude, the commanded tilt angle in rad for
          x (pitch) and y (roll)
  ``y``   the measured variable in SI units: roll or pitch angle in rad;
          altitude in m, positive up; x (north) or y (east) position in m
  ======  ==================================================================

- Rows of different loops may be interleaved; each loop's rows are sorted by
  ``t`` on reading. Rows holding ``nan`` or ``inf`` are dropped.

Example::

    # mrft-gcs loop csv v1
    # beta=-0.3 h=0.05
    t,loop,u,y
    0.000,roll,0.05,0.0012
    0.004,roll,0.05,0.0031
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mrft_gcs.logs._common import input_error, read_bytes
from mrft_gcs.logs.replay import DecodedLog
from mrft_gcs.loops import Loop

__all__ = ["decode_csv", "read_csv_metadata", "sniff_csv", "CSV_COLUMNS"]

#: Columns the header must name.
CSV_COLUMNS = ("t", "loop", "u", "y")
_LOOPS = {loop.value for loop in Loop}
_HINT = "see README 'Logs' for the CSV format (header t,loop,u,y)"


def _lines(path: str | Path, data: bytes) -> list[str]:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise input_error(path, f"not UTF-8 text (bad byte at offset {exc.start})",
                          "a CSV log must be UTF-8 text; " + _HINT) from None
    if "\0" in text:
        raise input_error(path, "binary data, not CSV text", _HINT)
    return text.splitlines()


def sniff_csv(head: bytes) -> bool:
    """True if ``head`` (the first bytes of a file) starts like the documented CSV."""
    try:
        text = head.decode("utf-8-sig", errors="strict")
    except UnicodeDecodeError:
        # The head may cut a multi-byte character; judge what decodes.
        text = head[:-4].decode("utf-8-sig", errors="ignore")
    for line in text.splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        names = {c.strip().lower() for c in s.split(",")}
        return set(CSV_COLUMNS) <= names
    return False


def read_csv_metadata(path: str | Path) -> dict[str, str]:
    """The ``key=value`` metadata of a CSV log's comment lines.

    Parameters
    ----------
    path : str or Path
        The CSV file.

    Returns
    -------
    dict of str to str
        Keys and values as written (values are not converted).
    """
    meta: dict[str, str] = {}
    for line in _lines(path, read_bytes(path)):
        s = line.strip()
        if s.startswith("#"):
            for token in s[1:].split():
                key, sep, value = token.partition("=")
                if sep and key:
                    meta[key] = value
    return meta


def decode_csv(path: str | Path) -> DecodedLog:
    """Decode a CSV log into per-loop tables (``loops``: t, u, y).

    Raises
    ------
    InputFileError
        Not UTF-8 text, no header or a header without ``t,loop,u,y``, a row with
        the wrong number of fields, a number that does not parse, an unknown loop
        name, or no data rows.
    """
    raw = read_bytes(path)
    lines = _lines(path, raw)
    header: list[str] | None = None
    cols: tuple[int, int, int, int] = (0, 0, 0, 0)
    rows: dict[str, list[tuple[float, float, float]]] = {}
    for number, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = [f.strip() for f in s.split(",")]
        if header is None:
            header = [f.lower() for f in fields]
            missing = [c for c in CSV_COLUMNS if c not in header]
            if missing:
                raise input_error(path, f"line {number}: header {s[:60]!r} lacks column(s) "
                                        f"{', '.join(missing)}", _HINT)
            cols = tuple(header.index(c) for c in CSV_COLUMNS)  # type: ignore[assignment]
            continue
        if len(fields) < len(header) and number == len(lines) and not raw.endswith(b"\n"):
            break  # a last row cut short: the file is truncated (log_truncation says so)
        if len(fields) != len(header):
            raise input_error(path, f"line {number}: {len(fields)} fields, the header has "
                                    f"{len(header)}", _HINT)
        it, il, iu, iy = cols
        loop = fields[il].lower()
        if loop not in _LOOPS:
            raise input_error(path, f"line {number}: unknown loop {fields[il][:20]!r} "
                                    f"(expected one of {', '.join(sorted(_LOOPS))})", _HINT)
        try:
            row = (float(fields[it]), float(fields[iu]), float(fields[iy]))
        except ValueError:
            raise input_error(path, f"line {number}: t, u and y must be numbers", _HINT) from None
        rows.setdefault(loop, []).append(row)
    if header is None:
        raise input_error(path, "no header line (only comments or blank lines)", _HINT)
    if not rows:
        raise input_error(path, "no data rows after the header", _HINT)
    loops = {k: np.asarray(v, dtype=float).reshape(-1, 3) for k, v in rows.items()}
    return DecodedLog(loops=loops, source=str(path))
