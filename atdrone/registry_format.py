"""How ``atdrone registry`` prints a table: aligned text fitted to the terminal, CSV or JSON, and one member.

A table cell is short (floats to 4 significant digits, lists comma-joined, nothing as
``-``); CSV and JSON carry every value in full. A table too wide for the terminal has its
widest text columns cut with ``…`` (never id, generation or status), then columns left out
from the right, which a last line says.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
from collections.abc import Sequence
from typing import Any

import pandas as pd

from atdrone.registry import RegistryError

FORMATS = ("table", "csv", "json")
_KEEP_WHOLE = frozenset({"id", "generation", "status"})  # never cut to fit the terminal
_GAP = "  "


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _missing(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def _cell(value: Any) -> str:
    """A value as a short table cell: floats to 4 significant digits, lists comma-joined, nothing as '-'."""
    if _missing(value):
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return ",".join(map(str, value)) or "-"
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True)
    return str(value)


def _full(value: Any) -> str:
    """A value in full: floats with every digit, lists and dicts as JSON, nothing as ''."""
    if _missing(value):
        return ""
    if isinstance(value, list | dict):
        return json.dumps(value, sort_keys=True)
    return str(value)


def terminal_width() -> int | None:
    """The width to fit: $COLUMNS, else the terminal's; None when stdout is not a terminal (nothing cut)."""
    columns = os.environ.get("COLUMNS", "")
    if columns.isdigit() and int(columns) > 0:
        return int(columns)
    return shutil.get_terminal_size().columns if sys.stdout.isatty() else None


def _is_numeric_column(values: Sequence[Any]) -> bool:
    present = [v for v in values if not _missing(v)]
    return bool(present) and all(isinstance(v, int | float) and not isinstance(v, bool) for v in present)


def format_table(frame: pd.DataFrame, width: int | None = None) -> str:
    """``frame`` as an aligned text table within ``width`` characters.

    Too wide: the widest text columns (never id, generation or status) are cut with '…'
    down to their header's width, then columns are left out from the right, which a
    last line says.
    """
    headers = [str(c) for c in frame.columns]
    numeric = [_is_numeric_column(list(frame[c])) for c in frame.columns]
    cells = [[_cell(v) for v in frame[c]] for c in frame.columns]
    widths = [max([len(h), *map(len, col)]) for h, col in zip(headers, cells, strict=True)]
    hidden = 0
    if width is not None:
        hidden = _fit(headers, numeric, widths, width)
    shown = len(headers) - hidden
    lines = [_line(headers[:shown], widths, numeric)]
    lines += [_line([col[i] for col in cells[:shown]], widths, numeric) for i in range(len(frame))]
    if hidden:
        lines.append(f"(+{hidden} columns: use --columns or --format csv)")
    return "\n".join(lines)


def _fit(headers: Sequence[str], numeric: Sequence[bool], widths: list[int], width: int) -> int:
    """Narrow ``widths`` in place to fit ``width``; return how many columns to leave out on the right."""
    shown = len(headers)

    def excess() -> int:
        return sum(widths[:shown]) + len(_GAP) * (shown - 1) - width

    while excess() > 0:
        cuttable = [
            i
            for i in range(shown)
            if not numeric[i] and headers[i] not in _KEEP_WHOLE and widths[i] > max(len(headers[i]), 6)
        ]
        if cuttable:
            i = max(cuttable, key=lambda j: widths[j])
            widths[i] = max(len(headers[i]), 6, widths[i] - excess())
        elif shown > 1:
            shown -= 1
        else:
            break
    return len(headers) - shown


def _line(values: Sequence[str], widths: Sequence[int], numeric: Sequence[bool]) -> str:
    parts = []
    for value, w, right in zip(values, widths, numeric, strict=False):
        text = value if len(value) <= w else value[: w - 1] + "…"
        parts.append(text.rjust(w) if right else text.ljust(w))
    return _GAP.join(parts).rstrip()


def format_csv(frame: pd.DataFrame) -> str:
    """``frame`` as CSV with every value in full (lists and dicts as JSON text)."""
    return frame.map(_full).to_csv(index=False).rstrip("\n")


def format_json(frame: pd.DataFrame) -> str:
    """``frame`` as a JSON array of objects, values as they are (NaN as null)."""
    records = [{k: (None if _missing(v) else v) for k, v in row.items()} for row in frame.to_dict("records")]
    return json.dumps(records, indent=2, default=str)


def format_frame(frame: pd.DataFrame, fmt: str, empty: str) -> str:
    """``frame`` as ``fmt`` (table, csv or json); a table with no rows is the line ``empty``."""
    if fmt == "csv":
        return format_csv(frame)
    if fmt == "json":
        return format_json(frame)
    if fmt != "table":
        raise RegistryError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    return format_table(frame, terminal_width()) if len(frame) else empty


def format_member(member: dict[str, Any]) -> str:
    """Every field of a member in full, one ``key: value`` line each; tags and metrics one line per key, sorted.

    Parents are comma-separated, a missing value is ``(none)``; nothing is cut.
    """
    lines = []
    for key, value in member.items():
        if isinstance(value, dict):
            lines.append(f"{key}:" if value else f"{key}: {{}}")
            lines += [f"  {k}: {_full(value[k])}" for k in sorted(value)]
        elif isinstance(value, list):
            lines.append(f"{key}: {', '.join(map(str, value))}")
        else:
            lines.append(f"{key}: {'(none)' if _missing(value) else _full(value)}")
    return "\n".join(lines)
