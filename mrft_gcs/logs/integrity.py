"""Whether a log ends inside a record: a file cut short (copied or read while the logger
was still writing, a download that stopped, a full disk).

The readers use every whole record and drop a cut last one silently; these walkers follow
each format's framing to its end so that the cut can be reported. They read the framing
only (lengths), never the content: a damaged record in the middle is the readers' business.
"""

from __future__ import annotations

from mrft_gcs.logs.tlog import _STX

__all__ = ["tlog_tail", "ulog_tail", "dataflash_tail", "csv_tail"]

_ULOG_HEADER = 16
_DF_HEAD = b"\xa3\x95"
_DF_FMT, _DF_FMT_LEN = 0x80, 89


def tlog_tail(buf: bytes) -> int:
    """Bytes at the end of a .tlog that do not make a whole record (8-byte stamp + frame)."""
    n, p = len(buf), 0
    while p + 9 <= n:
        stx = buf[p + 8]
        if stx == 0xFD:
            if p + 11 > n:
                return n - p
            end = p + 20 + buf[p + 9] + (13 if buf[p + 10] & 1 else 0)
        elif stx == 0xFE:
            end = p + 16 + buf[p + 9]
        else:  # not a record start: resynchronise on the next STX, as the reader does
            m = _STX.search(buf, p + 9)
            if m is None:
                return 0
            p = m.start() - 8
            continue
        if end > n:
            return n - p
        p = end
    return n - p


def ulog_tail(buf: bytes) -> int:
    """Bytes at the end of a ULog after its last whole message (3-byte header + payload)."""
    n, p = len(buf), _ULOG_HEADER
    while p + 3 <= n:
        end = p + 3 + (buf[p] | (buf[p + 1] << 8))
        if end > n:
            return n - p
        p = end
    return max(n - p, 0)


def dataflash_tail(buf: bytes) -> int:
    """Bytes at the end of a DataFlash log in a record cut by the end of the file."""
    lengths = [0] * 256
    lengths[_DF_FMT] = _DF_FMT_LEN
    n, p = len(buf), 0
    while p + 3 <= n:
        length = lengths[buf[p + 2]] if buf[p] == 0xA3 and buf[p + 1] == 0x95 else 0
        if length:
            if p + length > n:
                return n - p
            if buf[p + 2] == _DF_FMT and buf[p + 4] >= 3 and not lengths[buf[p + 3]]:
                lengths[buf[p + 3]] = buf[p + 4]  # a type's length, from its FMT record
            p += length
            continue
        q = buf.find(_DF_HEAD, p + 1)
        if q < 0:
            return 0
        p = q
    return n - p if p < n and buf[p] == 0xA3 else 0  # a record header cut itself


def csv_tail(text: str) -> int:
    """Characters of a last CSV row cut short (no newline, fewer fields than the header)."""
    if not text or text.endswith("\n"):
        return 0
    rows = [r for r in text.splitlines() if r.strip() and not r.lstrip().startswith("#")]
    if len(rows) < 2:
        return 0
    return len(rows[-1]) if rows[-1].count(",") < rows[0].count(",") else 0
