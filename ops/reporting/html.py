"""The catalog report's HTML building blocks (``ops.reporting.report``): escaping, number and duration
formatting, inline PNG images (data URIs, figures rendered off-screen, previews read and scaled) and tables."""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def esc(value: Any) -> str:
    return html.escape("" if value is None else str(value), quote=True)


def fmt_s(seconds: float) -> str:
    """A duration for people: seconds, minutes or hours."""
    if not math.isfinite(seconds):
        return "-"
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def fmt(value: Any, digits: int = 3) -> str:
    """A value for a table cell: ``digits`` significant digits for floats, ``-`` for none."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.{digits}g}"
    return str(value)


def png_uri(data: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def figure_png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def img(data: bytes, alt: str, cls: str = "") -> str:
    return f'<img class="{esc(cls)}" alt="{esc(alt)}" src="{png_uri(data)}">'


def html_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], cls: str = "") -> str:
    """A table of escaped text cells."""
    head = "".join(f"<th>{esc(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{esc(cls)}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def preview_png(path: Path | None, max_width: int, max_height: int | None = None) -> tuple[bytes | None, str]:
    """The preview PNG's bytes (scaled down to fit ``max_width`` × ``max_height``), or None and why not."""
    if path is None:
        return None, "no preview path in the row"
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, f"preview unreadable: {exc.strerror or exc} ({path})"
    if not data.startswith(PNG_SIGNATURE):
        return None, f"preview is not a PNG ({path})"
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            im.load()  # decode fully here: a truncated PNG must not become a broken image in the page
            scale = min(1.0, max_width / im.width, (max_height or im.height) / im.height)
            if scale < 1.0:
                scaled = im.resize((max(1, round(im.width * scale)), max(1, round(im.height * scale))))
                buf = io.BytesIO()
                scaled.save(buf, format="PNG", optimize=True)
                data = buf.getvalue()
    except Exception as exc:
        return None, f"preview does not decode: {exc} ({path})"
    return data, ""
