"""The catalog gallery (``morpheus3d report`` writes it beside the report): every asset's turntable linking its
viewer page (``ops.engine.viewer_page``), filterable by verdict with CSS alone.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ops.engine.viewer_page import PAGE_CSS
from ops.reporting.html import esc

GALLERY_FILE = "gallery.html"


def gallery_assets(rows: Sequence[dict[str, Any]], base: Path, page_dir: Path) -> list[dict[str, Any]]:
    """The gallery's cards from catalog rows (``ops.reporting.asset_metrics.asset_rows``): links relative to the
    gallery's folder, paths in the rows relative to ``base`` (the store root) when not absolute."""
    def resolved(path: str | None) -> Path | None:
        return None if not path else Path(path) if Path(path).is_absolute() else Path(base) / path

    def link(path: str | None) -> str | None:
        p = resolved(path)
        return None if p is None else os.path.relpath(p, page_dir)

    def thumb(row: dict[str, Any]) -> str | None:
        strip = resolved(row.get("preview_path"))  # the qa turntable strip; its animated GIF sits beside it
        gif = strip.with_suffix(".gif") if strip is not None else None
        return link(str(gif)) if gif is not None and gif.is_file() else link(row.get("preview_path"))

    return [{"key": r["photo_key"], "verdict": r.get("verdict") or "none", "sku": r.get("sku") or "",
             "viewer_href": link(r.get("viewer_path")) or link(r.get("glb_path")) or "#",
             "thumb_href": thumb(r),
             "size_mm": {d: r[f"export_{d}_mm"] for d in ("width", "height", "depth")
                         if r.get(f"export_{d}_mm") is not None}} for r in rows]


def gallery_html(assets: Sequence[dict[str, Any]], title: str = "Morpheus3D catalog gallery") -> str:
    """Every asset's thumbnail (the turntable GIF) linking its viewer page; radio buttons filter by verdict (CSS
    only). Each asset:
    ``key``, ``verdict``, ``viewer_href``, ``thumb_href`` (or None), ``size_mm`` (or {}), ``sku``."""
    verdicts = ("pass", "warn", "fail")
    counts = {v: sum(a["verdict"] == v for a in assets) for v in verdicts}
    radios = f'<input type="radio" name="f" id="f-all" checked><label for="f-all">all ({len(assets)})</label>'
    radios += "".join(f'<input type="radio" name="f" id="f-{v}"><label for="f-{v}">{v} ({counts[v]})</label>'
                      for v in verdicts)
    hide = "".join(f"#f-{v}:checked~.grid .card:not(.{v}){{display:none}}" for v in verdicts)
    cards = []
    for a in assets:
        size = a.get("size_mm") or {}
        dims = " × ".join(f"{size[k]:.0f}" for k in ("width", "height", "depth") if k in size)
        thumb = (f'<img src="{esc(a["thumb_href"])}" alt="{esc(a["key"])}" loading="lazy">' if a.get("thumb_href")
                 else '<div class="nothumb">no preview</div>')
        verdict = a["verdict"] if a["verdict"] in verdicts else "none"
        cards.append(f'<a class="card {esc(verdict)}" href="{esc(a["viewer_href"])}">{thumb}'
                     f'<span class="key">{esc(a["key"])}</span><span class="sku">{esc(a.get("sku", ""))}</span>'
                     f'<span class="verdict {esc(verdict)}">'
                     f'{esc(a["verdict"])}</span><span class="dims">{esc(dims + " mm" if dims else "")}</span></a>')
    css = (PAGE_CSS + ".grid{display:flex;flex-wrap:wrap;gap:.8em;margin-top:1em}"
           ".card{display:flex;flex-direction:column;width:200px;border:1px solid #ddd;padding:.4em;color:inherit;"
           "text-decoration:none}.card img{width:100%}.key{font-weight:600}.dims{color:#555;font-size:.9em}"
           ".nothumb{height:100px;background:#eee}input{margin-left:1em}" + hide)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{esc(title)}</title><style>{css}</style></head><body><h1>{esc(title)}</h1>"
            f'{radios}<div class="grid">{"".join(cards)}</div></body></html>\n')
