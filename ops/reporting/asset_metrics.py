"""The catalog report's ``metrics`` section: a table with a row per asset (its turntable thumbnail, verdict, key
metrics, build time, last run) and, from ``HISTOGRAM_MIN_ASSETS`` assets up, a histogram per numeric
``metric_*`` column. Below that a histogram of a handful of values says less than the table's numbers.

An asset is a photo's newest finished row, so each asset (each piece of QA work) counts once however often
a cached re-run reported it again."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from matplotlib.figure import Figure

from assets_store.catalog import latest_rows
from ops.reporting.html import esc, figure_png, fmt, fmt_s, img, preview_png
from ops.reporting.report_sections import HISTOGRAM_MIN_ASSETS, KEY_METRICS, ReportOptions, page_link, resolve_path
from ops.reporting.stage_columns import BUILD_SUFFIX, float_column, wall_stages

__all__ = ["HISTOGRAM_MIN_ASSETS", "asset_rows", "asset_table", "histograms", "metrics_section", "numeric_metrics"]


def asset_rows(table: pa.Table) -> pa.Table:
    """Each photo's newest row that is not ``failed`` (its current asset), sorted by photo key."""
    if table.num_rows == 0 or "photo_key" not in table.column_names:
        return table.slice(0, 0)
    if "status" in table.column_names:
        table = table.filter(pc.fill_null(pc.not_equal(table["status"], "failed"), True))
    return latest_rows(table) if table.num_rows else table


def numeric_metrics(table: pa.Table) -> list[str]:
    """The ``metric_*`` columns holding numbers or booleans, in column order."""
    out = []
    for name in table.column_names:
        t = table.schema.field(name).type
        if name.startswith("metric_") and (pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t)):
            out.append(name)
    return out


def histograms(assets: pa.Table) -> str:
    """A histogram (a bar pair for booleans) per numeric metric, one value per asset."""
    cards = []
    for name in numeric_metrics(assets):
        values = float_column(assets, name)
        finite = values[np.isfinite(values)]
        nulls = int(np.isnan(values).sum()) if values.size else 0
        odd = int(values.size - finite.size - nulls)  # ±inf (NaN counts with the nulls: a metric not computed)
        caption = f"{finite.size} values"
        if nulls:
            caption += f", {nulls} null/NaN"
        if odd:
            caption += f", {odd} infinite (not drawn)"
        if finite.size == 0:
            cards.append(f'<figure class="metric"><figcaption><b>{esc(name)}</b>: no finite values '
                         f"({esc(caption)})</figcaption></figure>")
            continue
        fig = Figure(figsize=(3.4, 2.3))
        ax = fig.add_subplot()
        if pa.types.is_boolean(assets.schema.field(name).type):
            trues = int(finite.sum())
            ax.bar(["false", "true"], [finite.size - trues, trues], color=["#c55", "#5a5"])
        else:
            bins = min(30, max(5, int(np.sqrt(finite.size))))
            ax.hist(finite, bins=bins, color="#4a78b0")
            ax.axvline(float(np.median(finite)), color="k", lw=1, ls="--")
            caption += f", median {fmt(float(np.median(finite)), 4)}"
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=7)
        fig.tight_layout()
        cards.append(f'<figure class="metric">{img(figure_png(fig), f"histogram of {name}")}'
                     f"<figcaption>{esc(caption)}</figcaption></figure>")
    return '<div class="grid">' + "".join(cards) + "</div>" if cards else \
        '<p class="empty">No numeric metric_* columns.</p>'


def _build_s(row: dict[str, Any], stages: list[str]) -> float:
    times = [row.get(f"{s}{BUILD_SUFFIX}") for s in stages]
    finite = [float(t) for t in times if isinstance(t, (int, float)) and math.isfinite(t)]
    return sum(finite) if finite else math.nan


def asset_table(assets: pa.Table, base: Any, options: ReportOptions) -> str:
    """One row per asset (the first ``options.asset_table_max`` by photo key): thumbnail, verdict, key metrics,
    the time its outputs took to make, its newest run."""
    metrics = [m for m in KEY_METRICS if m in assets.column_names and assets[m].null_count < assets.num_rows]
    stages = wall_stages(assets.column_names)
    head = ["photo", "turntable", "verdict", *(m.removeprefix("metric_") for m in metrics), "build time",
            "newest run"]
    body = []
    for row in assets.slice(0, options.asset_table_max).to_pylist():
        data, why = preview_png(resolve_path(row.get("preview_path"), base), options.thumbnail_max_width,
                                options.thumbnail_height)
        thumb = img(data, f"turntable of {row.get('photo_key')}", "thumb") if data else \
            f'<span class="nopreview">{esc(why)}</span>'
        created = row.get("created_at")
        newest = f"{row.get('run_id')} ({row.get('status')}, {created:%Y-%m-%d %H:%M} UTC)" \
            if created is not None else str(row.get("run_id"))
        viewer = resolve_path(row.get("viewer_path"), base)
        key = esc(row.get("photo_key"))
        if viewer is not None:
            key = f'<a href="{esc(page_link(viewer, options))}" title="turn it in 3D, at its real size">{key}</a>'
        cells = [key, thumb, esc(row.get("verdict") or "-"),
                 *(esc(fmt(row.get(m), 4)) for m in metrics), esc(fmt_s(_build_s(row, stages))), esc(newest)]
        body.append(f'<tr class="asset" data-photo-key="{esc(row.get("photo_key"))}">'
                    + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    more = assets.num_rows - len(body)
    tail = f"<p>… and {more} more assets (the histograms above cover all of them).</p>" if more > 0 else ""
    return ('<table class="assets"><thead><tr>' + "".join(f"<th>{esc(h)}</th>" for h in head)
            + "</tr></thead><tbody>" + "".join(body) + "</tbody></table>" + tail)


def metrics_section(assets: pa.Table, base: Any, options: ReportOptions) -> str:
    """The per-asset table, preceded by the metrics' histograms from ``options.histogram_min_assets`` assets up."""
    n = assets.num_rows
    if n == 0:
        return '<p class="empty">No finished assets.</p>'
    if n >= options.histogram_min_assets:
        intro = f"<p>{n} assets, each counted once (its newest finished run).</p>" + histograms(assets)
    else:
        intro = (f"<p>{n} asset{'s' if n != 1 else ''}, each counted once (its newest finished run); the metrics' "
                 f"histograms appear from {options.histogram_min_assets} assets up.</p>")
    return intro + asset_table(assets, base, options)
