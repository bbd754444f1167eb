"""The catalog report: one self-contained HTML page over the run catalog (``morpheus3d report``).

Sections (each a ``<section id=...>`` with an ``<h2>``): ``summary`` (counts by status and verdict, photos,
runs, time span, wall time per stage), ``metrics`` (a table with a row per asset and its turntable thumbnail;
from ``HISTOGRAM_MIN_ASSETS`` assets up also a histogram per numeric ``metric_*`` column), ``curves``
(reference PSNR against wall time from the rows' ``runlog_<stage>`` files), ``worst`` (the worst assets with
their previews) and ``failures`` (failed rows with their reasons).

Each piece of work counts once (``ops.reporting.stage_columns.count_work_once``): a cached re-run's rows are
counted as runs that found everything cached, add no wall time, and each asset is one row of the metrics.

Everything is inline: figures and previews are base64 PNG data URIs, the CSS is a ``<style>`` element, there
is no script, so the page can be mailed or archived and opens without a network. Every text taken from the
catalog is escaped. Figures are drawn with Matplotlib's Agg canvas directly (no pyplot: no global backend
state, safe inside a Dagster process). Paths in the rows (previews, run logs) are resolved against the store
root when relative.

The page's building blocks (escaping, formatting, images, tables) are in ``ops.reporting.html``, the sections and
their ``ReportOptions`` in ``ops.reporting.report_sections``; this module assembles the page and writes it.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import replace
from pathlib import Path

from assets_store.atomic import atomic_write_text
from assets_store.catalog import Catalog, CatalogRead, latest_rows
from ops.reporting.asset_metrics import asset_rows, metrics_section
from ops.reporting.html import esc
from ops.reporting.report_sections import (
    ReportOptions,
    curves_section,
    failures_section,
    summary_section,
    worst_section,
)
from ops.reporting.stage_columns import count_work_once, current_stage_columns

SECTIONS = (("summary", "Summary"), ("metrics", "Metrics per asset"), ("curves", "Error against run time"),
            ("worst", "Worst assets"), ("failures", "Failures"))


# ---------------------------------------------------------------------------------------------- the page

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0 auto;max-width:1400px;padding:1em 2em;
color:#222}
nav a{margin-right:1em}
section{border-top:1px solid #ccc;margin-top:1.5em}
table{border-collapse:collapse;margin:.5em 1em .5em 0;font-size:.9em}
th,td{border:1px solid #ddd;padding:.25em .6em;text-align:left;vertical-align:top}
th{background:#f3f3f3}
.row{display:flex;flex-wrap:wrap}
.grid{display:flex;flex-wrap:wrap;gap:.5em}
figure{margin:.3em}
figcaption{font-size:.8em;color:#555;max-width:40em}
.warning{background:#fff4d6;border:1px solid #e0b84a;padding:.2em 1em}
.empty{color:#777;font-style:italic}
ol.worst{list-style:none;padding:0}
li.worst-asset{border:1px solid #ddd;margin:.6em 0;padding:.4em .8em;display:flex;flex-wrap:wrap;gap:0 2em;
align-items:flex-start}
li.worst-asset h3{flex-basis:100%;margin:.2em 0}
li.worst-asset img.preview{max-width:100%;display:block}
dl{display:grid;grid-template-columns:max-content auto;gap:.1em 1em;font-size:.9em;margin:.4em 0}
dt{color:#555}
dd{margin:0;word-break:break-all}
table.failures td:nth-child(6){color:#a00}
table.assets img.thumb{display:block}
"""


def build_report(
    catalog: Catalog,
    since: dt.date | dt.datetime | None = None,
    base_dir: Path | None = None,
    options: ReportOptions | None = None,
    now: dt.datetime | None = None,
    scanned: CatalogRead | None = None,
) -> str:
    """The report page as a string. ``base_dir``: what relative paths in the rows are relative to (the store
    root; default: the catalog folder's parent). ``scanned``: the catalog's rows since ``since`` when the
    caller has read them already (``catalog.scan(since)``; a large catalog is read once, not per page)."""
    options = options or ReportOptions()
    base = Path(base_dir) if base_dir is not None else catalog.root.parent
    scanned = scanned if scanned is not None else catalog.scan(since)
    read = replace(scanned, table=count_work_once(current_stage_columns(scanned.table)))
    table = read.table
    latest = latest_rows(table) if table.num_rows and "photo_key" in table.column_names else table.slice(0, 0)
    bodies = {"summary": summary_section(read, catalog.root, since)}
    if table.num_rows == 0:
        for sid, _ in SECTIONS[1:]:
            bodies[sid] = '<p class="empty">The catalog is empty.</p>'
    else:
        bodies["metrics"] = metrics_section(asset_rows(table), base, options)
        bodies["curves"] = curves_section(latest, base, options)
        bodies["worst"] = worst_section(latest, base, options)
        bodies["failures"] = failures_section(table, options)
    now = now or dt.datetime.now(dt.timezone.utc)
    nav = "".join(f'<a href="#{sid}">{esc(title)}</a>' for sid, title in SECTIONS)
    sections = "".join(f'<section id="{sid}"><h2>{esc(title)}</h2>{bodies[sid]}</section>' for sid, title in SECTIONS)
    scope = f", rows since {since}" if since is not None else ""
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>Morpheus3D catalog report</title><style>{_CSS}</style></head><body>"
        f"<h1>Morpheus3D catalog report</h1><p class=\"meta\">Catalog <code>{esc(catalog.root)}</code>{esc(scope)}; "
        f"generated {esc(now.isoformat(timespec='seconds'))}.</p><nav>{nav}</nav>{sections}</body></html>\n"
    )


def write_report(path: Path, page: str) -> Path:
    """Write the page atomically: a reader (or a browser refresh) never sees half a report."""
    return atomic_write_text(Path(path), page)
