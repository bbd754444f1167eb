"""The catalog report's sections (``ops.reporting.report`` assembles the page): ``summary``, ``curves``,
``worst`` and ``failures``, each a function returning its HTML (``metrics`` is in ``ops.reporting.asset_metrics``);
the options they take (``ReportOptions``) and the helper resolving the rows' paths.

The sections read the catalog table after ``ops.reporting.stage_columns.count_work_once``: wall times are
summed from ``<stage>_work_s`` (each piece of work once, cached re-runs none), curves are shifted by
``<stage>_build_s`` (the time the output took to make, whichever run made it)."""

from __future__ import annotations

import datetime as dt
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from matplotlib.figure import Figure

from assets_store.catalog import CatalogRead
from ops.reporting.html import esc, figure_png, fmt, fmt_s, html_table, img, preview_png
from ops.reporting.stage_columns import BUILD_SUFFIX, WORK_SUFFIX, float_column, string_column, wall_stages

KEY_METRICS = ("metric_ref_psnr", "metric_ssim_in", "metric_mask_iou", "metric_lpips", "metric_colour_deviation",
               "metric_hf_ratio")
HISTOGRAM_MIN_ASSETS = 20  # fewer assets: the metrics section is the per-asset table only (few values: no shape)


@dataclass(frozen=True)
class ReportOptions:
    worst_n: int = 12  # assets in the worst list
    curves_n: int = 20  # photos drawn one by one in the error-against-time figure
    median_n: int = 200  # photos whose run logs make up the median curve (read: ~1 ms each)
    max_failures: int = 500  # rows in the failures table (the rest counted)
    preview_max_width: int = 1200  # wider previews are scaled down so the page stays mailable
    histogram_min_assets: int = HISTOGRAM_MIN_ASSETS  # assets from which the metrics section draws histograms
    asset_table_max: int = 200  # rows of the per-asset table (the rest counted; the histograms cover them)
    thumbnail_height: int = 64  # the per-asset table's turntable strips, scaled to this height …
    thumbnail_max_width: int = 512  # … and at most this width
    page_dir: Path | None = None  # where the page is written: links to the viewer pages are relative to it


def page_link(path: Path, options: ReportOptions) -> str:
    """A link from the page to a file: relative to ``options.page_dir`` when set, else a file:// URI."""
    return os.path.relpath(path, options.page_dir) if options.page_dir is not None else path.resolve().as_uri()


# ---------------------------------------------------------------------------------------------- helpers


def resolve_path(path: str | None, base: Path) -> Path | None:
    """A path from a row, relative ones taken from ``base`` (the store root)."""
    if not path:
        return None
    p = Path(path)
    return p if p.is_absolute() else base / p


def _counts(values: list[str | None]) -> list[tuple[str, int]]:
    out: dict[str, int] = {}
    for v in values:
        key = "(none)" if v is None else v
        out[key] = out.get(key, 0) + 1
    return sorted(out.items(), key=lambda kv: (-kv[1], kv[0]))


# ---------------------------------------------------------------------------------------------- sections


def summary_section(read: CatalogRead, catalog_root: Path, since: Any) -> str:
    table = read.table
    n = table.num_rows
    parts = []
    if read.skipped:
        items = "".join(f"<li><code>{esc(p)}</code>: {esc(why)}</li>" for p, why in read.skipped)
        parts.append(f'<div class="warning"><p>{len(read.skipped)} catalog file(s) could not be read; their rows '
                     f"are missing from this report:</p><ul>{items}</ul></div>")
    if n == 0:
        where = f" since {since}" if since is not None else ""
        parts.append(f'<p class="empty">The catalog at <code>{esc(catalog_root)}</code> holds no rows{esc(where)}.'
                     "</p>")
        return "".join(parts)
    created = [t for t in table["created_at"].to_pylist() if t is not None] if "created_at" in table.column_names \
        else []
    span = f"{min(created).isoformat(timespec='seconds')} to {max(created).isoformat(timespec='seconds')}" \
        if created else "-"
    photos = len({p for p in string_column(table, "photo_key") if p is not None})
    statuses = string_column(table, "status")
    runs: dict[str, bool] = {}  # run id -> whether it did work (a row not "cached")
    for run, status in zip(string_column(table, "run_id"), statuses, strict=True):
        if run is not None:
            runs[run] = runs.get(run, False) or status != "cached"
    worked = sum(runs.values())
    facts = [("rows (a photo in a run)", n), ("photos", photos), ("runs that did work", worked),
             ("runs that found everything cached", len(runs) - worked), ("time span (UTC)", span)]
    parts.append(html_table(["", ""], facts, "facts"))
    parts.append('<div class="row">' + html_table(["status", "rows"], _counts(statuses), "counts status")
                 + html_table(["verdict", "rows"], _counts(string_column(table, "verdict")), "counts verdict")
                 + "</div>")

    stages = [s for s in wall_stages(table.column_names) if f"{s}{WORK_SUFFIX}" in table.column_names]
    rows = []
    per_row = np.zeros(n)
    worked_rows = np.zeros(n, dtype=bool)
    for stage in stages:
        work = float_column(table, f"{stage}{WORK_SUFFIX}")  # null where cached or counted by an earlier row
        ok = work[np.isfinite(work)]
        per_row += np.nan_to_num(work, nan=0.0, posinf=0.0, neginf=0.0)
        worked_rows |= np.isfinite(work)
        if ok.size:
            rows.append((stage, ok.size, fmt_s(ok.sum()), fmt_s(ok.mean()), fmt_s(float(np.median(ok))),
                         fmt_s(float(np.percentile(ok, 95)))))
        else:
            rows.append((stage, 0, "-", "-", "-", "-"))
    if stages:
        done = per_row[worked_rows]
        rows.append(("all stages (per row with work)", done.size, *(
            (fmt_s(done.sum()), fmt_s(done.mean()), fmt_s(float(np.median(done))),
             fmt_s(float(np.percentile(done, 95)))) if done.size else ("-", "-", "-", "-"))))
        parts.append("<h3>Wall time per stage</h3><p>Each piece of work once: a stage's output counts in the run "
                     "that made it; a run that found it cached adds nothing.</p>")
        parts.append(html_table(["stage", "builds", "total", "mean", "median", "p95"], rows, "walltime"))
    return "".join(parts)


def _runlog_points(path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """(wall_s, ref_psnr) of the logged rows with a finite PSNR, sorted by time; and the log's last wall_s."""
    with pq.ParquetFile(str(path)) as pf:
        names = pf.schema_arrow.names
        if "wall_s" not in names:
            raise ValueError("no wall_s column")
        table = pf.read(columns=[c for c in ("wall_s", "ref_psnr") if c in names], use_threads=False)
    wall = float_column(table, "wall_s")
    psnr = float_column(table, "ref_psnr")
    end = float(np.nanmax(wall)) if np.isfinite(wall).any() else 0.0
    keep = np.isfinite(wall) & np.isfinite(psnr)
    order = np.argsort(wall[keep], kind="stable")
    return wall[keep][order], psnr[keep][order], end


Segment = tuple[np.ndarray, np.ndarray]  # (wall time since the run started, reference PSNR), time ascending


def _curve(row: dict[str, Any], stages: list[str], base: Path, problems: list[str]) -> list[Segment]:
    """A photo's reference PSNR against wall time since the run started, one segment per stage's log, each
    shifted by the wall time of the stages before it (the row's ``<stage>_build_s``, else the log's last time).

    Segments stay apart: each stage measures a different representation (field, mesh, texture), so a line
    from one stage's last value to the next one's first would draw a trend that was never measured.
    """
    segments = []
    offset = 0.0
    for stage in stages:
        end = 0.0
        path = resolve_path(row.get(f"runlog_{stage}"), base)
        if path is not None:
            try:
                t, v, end = _runlog_points(path)
                if t.size:
                    segments.append((t + offset, v))
            except FileNotFoundError:
                problems.append(f"{row.get('photo_key')}: {stage} log missing ({path})")
            except Exception as exc:  # a bad log costs its curve segment, never the report
                problems.append(f"{row.get('photo_key')}: {stage} log unreadable ({path}: {exc})")
        wall = row.get(f"{stage}{BUILD_SUFFIX}", row.get(f"{stage}_wall_s"))
        offset += float(wall) if isinstance(wall, (int, float)) and math.isfinite(wall) else end
    return segments


def _on_grid(segments: list[Segment], grid: np.ndarray) -> np.ndarray:
    """The curve's value at each grid time inside one of its segments (linear between logged points), else NaN."""
    out = np.full(grid.size, np.nan)
    for t, v in segments:
        inside = (grid >= t[0]) & (grid <= t[-1])
        out[inside] = np.interp(grid[inside], t, v)
    return out


def _spread(items: list[Any], k: int) -> list[Any]:
    """At most k items evenly spread over the list (its order kept): a deterministic sample."""
    if len(items) <= k:
        return items
    idx = np.linspace(0, len(items) - 1, k).round().astype(int)
    return [items[i] for i in sorted(set(idx.tolist()))]


def curves_section(latest: pa.Table, base: Path, options: ReportOptions) -> str:
    stages = wall_stages(latest.column_names)
    log_cols = [f"runlog_{s}" for s in stages if f"runlog_{s}" in latest.column_names]
    if not log_cols or latest.num_rows == 0:
        return '<p class="empty">No rows name run logs (runlog_&lt;stage&gt; columns).</p>'
    has_log = pc.is_valid(latest[log_cols[0]])
    for c in log_cols[1:]:
        has_log = pc.or_(has_log, pc.is_valid(latest[c]))
    candidates = latest.filter(has_log).to_pylist()  # sorted by photo_key (latest_rows)
    sample = _spread(candidates, options.median_n)
    drawn = {id(r) for r in _spread(sample, options.curves_n)}
    problems: list[str] = []
    curves = []
    for row in sample:
        segments = _curve(row, stages, base, problems)
        if segments:
            curves.append((row, segments))
    if not curves:
        detail = "".join(f"<li>{esc(p)}</li>" for p in problems[:20])
        return f'<p class="empty">No run log with reference PSNR could be read.</p><ul class="problems">{detail}</ul>'
    fig = Figure(figsize=(9, 4.5))
    ax = fig.add_subplot()
    shown = 0
    for row, segments in curves:
        if id(row) in drawn:
            # NaN between segments: one line (one colour) per photo, broken where the stage changes.
            t = np.concatenate([np.append(seg_t, np.nan) for seg_t, _ in segments])
            v = np.concatenate([np.append(seg_v, np.nan) for _, seg_v in segments])
            ax.plot(t, v, lw=0.9, alpha=0.6)
            shown += 1
    t_end = max(float(seg_t[-1]) for _, segments in curves for seg_t, _ in segments)
    grid = np.linspace(0.0, t_end, 400)
    # Every curve on a common time axis, only where it was measured; the median is drawn where at least half the
    # photos have a value, so it is not one photo's curve in the gaps and tails.
    stack = np.array([_on_grid(segments, grid) for _, segments in curves])
    covered = np.isfinite(stack).sum(axis=0)
    median = np.full(grid.size, np.nan)
    enough = covered >= max(1, math.ceil(len(curves) / 2))
    if enough.any():
        median[enough] = np.nanmedian(stack[:, enough], axis=0)
    ax.plot(grid, median, color="k", lw=2.5, label=f"median of {len(curves)} photos")
    ax.set_xlabel("wall time since the run started (s)")
    ax.set_ylabel("reference PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    caption = (f"{shown} photos drawn (thin lines, spread over the catalog's photos by key), the median over "
               f"{len(curves)} photos with readable logs (thick, where at least half of them have a value). Each "
               "stage's log is shifted by the wall time of the stages before it; lines break between stages.")
    out = f'<figure class="curves">{img(figure_png(fig), "reference PSNR against wall time")}' \
          f"<figcaption>{esc(caption)}</figcaption></figure>"
    if problems:
        items = "".join(f"<li>{esc(p)}</li>" for p in problems[:20])
        more = f"<li>… {len(problems) - 20} more</li>" if len(problems) > 20 else ""
        out += f'<p>{len(problems)} run log(s) missing or unreadable (skipped):</p><ul class="problems">{items}' \
               f"{more}</ul>"
    return out


def worst_order(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Worst first: verdict ``fail`` before the rest, then by ascending reference PSNR (no PSNR last)."""

    def key(row: dict[str, Any]) -> tuple[int, float]:
        psnr = row.get("metric_ref_psnr")
        value = float(psnr) if isinstance(psnr, (int, float)) and math.isfinite(psnr) else math.inf
        return (0 if row.get("verdict") == "fail" else 1, value)

    return sorted(rows, key=key)


def worst_section(latest: pa.Table, base: Path, options: ReportOptions) -> str:
    if latest.num_rows == 0:
        return '<p class="empty">No rows.</p>'
    rows = latest.to_pylist()
    if "status" in latest.column_names:
        rows = [r for r in rows if r.get("status") != "failed"]  # failed runs have no asset: see Failures
    worst = worst_order(rows)[: options.worst_n]
    if not worst:
        return '<p class="empty">No finished assets.</p>'
    metrics = [m for m in KEY_METRICS if m in latest.column_names]
    items = []
    for rank, row in enumerate(worst, 1):
        data, why = preview_png(resolve_path(row.get("preview_path"), base), options.preview_max_width)
        image = img(data, f"preview of {row.get('photo_key')}", "preview") if data else \
            f'<p class="nopreview">{esc(why)}</p>'
        psnr = row.get("metric_ref_psnr")
        psnr_attr = f"{psnr:.6g}" if isinstance(psnr, (int, float)) and math.isfinite(psnr) else ""
        numbers = "".join(f"<dt>{esc(m.removeprefix('metric_'))}</dt><dd>{esc(fmt(row.get(m), 4))}</dd>"
                          for m in metrics)
        checks = [f"{c.removeprefix('check_')}={v}" for c, v in row.items() if c.startswith("check_") and
                  v in ("fail", "warn")]
        facts = [("verdict", row.get("verdict")), ("failing checks", ", ".join(checks) or "-"),
                 ("reasons", row.get("reasons") or "-"), ("run", row.get("run_id")),
                 ("created", row.get("created_at")), ("asset", row.get("glb_path"))]
        facts_html = "".join(f"<dt>{esc(k)}</dt><dd>{esc(v)}</dd>" for k, v in facts)
        items.append(
            f'<li class="worst-asset" data-rank="{rank}" data-verdict="{esc(row.get("verdict") or "")}" '
            f'data-ref-psnr="{esc(psnr_attr)}" data-photo-key="{esc(row.get("photo_key"))}">'
            f'<h3>{rank}. {esc(row.get("photo_key"))}</h3>{image}<dl class="numbers">{numbers}</dl>'
            f'<dl class="facts">{facts_html}</dl></li>')
    note = (f"<p>The {len(worst)} worst of {len(rows)} photos' newest finished runs: verdict fail first, then by "
            "ascending reference PSNR.</p>")
    return note + '<ol class="worst">' + "".join(items) + "</ol>"


def failures_section(table: pa.Table, options: ReportOptions) -> str:
    if table.num_rows == 0 or "status" not in table.column_names:
        return '<p class="empty">No rows.</p>'
    failed = table.filter(pc.equal(table["status"], "failed"))
    if failed.num_rows == 0:
        return '<p class="empty">No failed rows.</p>'
    oldest = dt.datetime.min.replace(tzinfo=dt.timezone.utc)
    rows = sorted(failed.to_pylist(), key=lambda r: r.get("created_at") or oldest, reverse=True)  # newest first
    stages = wall_stages(table.column_names)
    out_rows = []
    for row in rows[: options.max_failures]:
        stage = next((s for s in stages if row.get(f"{s}_status") == "failed"), "-")
        created = row.get("created_at")
        out_rows.append((created.isoformat(timespec="seconds") if isinstance(created, dt.datetime) else created,
                         row.get("photo_key"), row.get("run_id"), row.get("preset"), stage,
                         row.get("failure_reason") or "-", row.get("reasons") or ""))
    more = f"<p>… and {len(rows) - options.max_failures} older failed rows.</p>" \
        if len(rows) > options.max_failures else ""
    head = f"<p>{len(rows)} failed rows, newest first.</p>"
    return head + html_table(["created (UTC)", "photo", "run", "preset", "failed stage", "failure reason", "reasons"],
                         out_rows, "failures") + more
