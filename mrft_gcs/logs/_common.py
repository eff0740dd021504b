"""Helpers shared by the log readers: reading a file whole, one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mrft_gcs.errors import InputFileError

__all__ = ["SUPPORTED", "input_error", "read_bytes", "read_head", "interp_columns"]

#: What the user is told the readers accept.
SUPPORTED = "dry-run reads .tlog, .ulg, .bin and .csv"


def input_error(path: str | Path, problem: str, todo: str = SUPPORTED) -> InputFileError:
    """An :class:`InputFileError` reading ``"<path>: <problem>; <todo>"``."""
    return InputFileError(f"{path}: {problem}; {todo}")


def read_bytes(path: str | Path, limit: int = -1) -> bytes:
    """Read a file (whole, or its first ``limit`` bytes).

    OS errors and empty files become :class:`InputFileError`.
    """
    try:
        with open(path, "rb") as f:
            data = f.read(limit)
    except FileNotFoundError:
        raise input_error(path, "no such file", "check the path") from None
    except IsADirectoryError:
        raise input_error(path, "is a directory, not a log file",
                          "give the log file itself") from None
    except OSError as exc:
        raise input_error(path, f"cannot be read ({exc.strerror or exc})",
                          "check the path and its permissions") from None
    if not data:
        raise input_error(path, "empty file (0 bytes)", "the log was not written; " + SUPPORTED)
    return data


def read_head(path: str | Path, n: int = 64) -> bytes:
    """The first ``n`` bytes of a file, for detecting its format."""
    return read_bytes(path, n)


def interp_columns(t: np.ndarray, t_src: np.ndarray, values: np.ndarray,
                   max_gap_s: float = 0.1) -> np.ndarray:
    """Interpolate each column of ``values`` (sampled at ``t_src``) linearly at ``t``.

    Times up to ``max_gap_s`` outside ``t_src`` take the nearest end value; further
    out the result is NaN (the row is then dropped as non-finite).

    Parameters
    ----------
    t : ndarray, shape (N,)
    t_src : ndarray, shape (M,)
    values : ndarray, shape (M, k)

    Returns
    -------
    ndarray, shape (N, k)
    """
    if len(t_src) == 0:
        return np.full((len(t), values.shape[1]), np.nan)
    order = np.argsort(t_src, kind="stable")
    t_src, values = t_src[order], values[order]
    out = np.column_stack([np.interp(t, t_src, values[:, j]) for j in range(values.shape[1])])
    out[(t < t_src[0] - max_gap_s) | (t > t_src[-1] + max_gap_s)] = np.nan
    return out
