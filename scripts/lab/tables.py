"""The number format of every generated table, and a result folder's two files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def fmt(v: Any, digits: int = 3) -> str:
    """``v`` in a table cell: ``–`` for ``None``, floats to ``digits`` significant digits, anything else as is."""
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def pm(v: float | None, half: float | None) -> str:
    """A mean and its interval's half-width in a cell: ``v ± half`` (just ``v`` without an interval)."""
    return fmt(v) if half is None else f"{fmt(v)} ± {fmt(half, 2)}"


def write_result(out: Path, name: str, data: Any, table: str, meta: dict[str, Any]) -> None:
    """``out/summary.json`` (``{"meta": meta, name: data}``) and ``out/<name>.md`` (the Markdown ``table``)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps({"meta": meta, name: data}, indent=1, default=str))
    (out / f"{name}.md").write_text(table)
