"""The HTML of ``endomeasure report``: a Jinja2 template filled with the report's context.

The template (``templates/report.html.j2``) is the page's whole layout: plain HTML and
CSS for screen and print, figures embedded as base64 PNG, no network, no script beyond
a check that every figure decoded. Numbers are printed with :func:`_number` and carry
their full value in a ``data-value`` attribute, so that a test (or a script) reads what
the page shows without parsing formatted text. The file is written atomically.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

__all__ = ["render_report"]

_TEMPLATE = "report.html.j2"


def _number(value: Any, digits: int = 4) -> str:
    """A number to ``digits`` significant digits; ``-`` for a missing or non-finite one."""
    if value is None or not isinstance(value, (int, float)) or not math.isfinite(value):
        return "-"
    if isinstance(value, int):
        return str(value)
    return f"{value:.{digits}g}"


def _percent(value: Any, digits: int = 1) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value:.{digits}f} %"


def _environment():
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("endomeasure.io", "templates"),
        autoescape=jinja2.select_autoescape(["html", "j2"]),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = _number
    env.filters["pct"] = _percent
    env.filters["raw"] = lambda v: "" if v is None else repr(v)
    return env


def render_report(context: dict[str, Any], out: str | os.PathLike) -> Path:
    """Render the report page of ``context`` to ``out`` (atomically: a temporary file
    beside it, renamed over it)."""
    from endomeasure.io.outputs import atomic_write

    html = _environment().get_template(_TEMPLATE).render(**context)
    return atomic_write(out, lambda tmp: tmp.write_text(html, encoding="utf-8"))
