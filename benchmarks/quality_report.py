"""Markdown tables and plots of the quality benchmark (``benchmarks/quality.py``)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from assets_store.atomic import atomic_write
from benchmarks.ablations import ROWS, mean_by_row
from benchmarks.error_time import POINTS

_COLUMNS = (("novel_psnr", "novel PSNR (dB) ↑", 2), ("detail_psnr", "detail PSNR (dB) ↑", 2),
            ("novel_ssim", "SSIM ↑", 4), ("hf_ratio", "HF ratio (→1)", 3),
            ("colour_deviation", "colour dev. ↓", 4), ("chamfer", "Chamfer ↓", 4), ("fscore", "F-score ↑", 3),
            ("ref_psnr", "ref. PSNR (dB)", 2))


def _fmt(value: Any, digits: int) -> str:
    if value is None:
        return "—"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return f"{value:.{digits}f}"


def ablation_markdown(records: list[dict[str, Any]]) -> str:
    means = mean_by_row(records)
    head = "| row | " + " | ".join(c[1] for c in _COLUMNS) + " | scenes | paper's finding |"
    rule = "|---|" + "---:|" * (len(_COLUMNS) + 1) + "---|"
    lines = []
    for table, title in (("main", "Ablation of the 2D prior (paper Fig. 7–9, §5.5)"),
                         ("k2d", "Prior weight k2D (paper Table 2)"), ("r", "Frequency bound r (paper Table 3)")):
        lines += [f"### {title}", "", head, rule]
        rows = [("stage1", "stage 1 output (before any stage-2 row)")] if table == "main" else []
        rows += [(row.name, row.paper) for row in ROWS if row.table == table]
        for name, paper in rows:
            m = means.get(name)
            if m is None:
                continue
            cells = " | ".join(_fmt(m.get(key), d) for key, _, d in _COLUMNS)
            lines.append(f"| {name} | {cells} | {int(m['scenes'] or 0)} | {paper} |")
        lines.append("")
    failed = [r for r in records if "error" in r]
    if failed:
        lines += ["", "Failed runs: " + "; ".join(f"{r['scene']}/{r['row']}: {r['error']}" for r in failed)]
    return "\n".join(lines) + "\n"


def per_scene_markdown(records: list[dict[str, Any]], rows: tuple[str, ...] = ("base", "full_pass_2d", "ours")
                       ) -> str:
    scenes = list(dict.fromkeys(r["scene"] for r in records))
    lines = ["| scene | " + " | ".join(f"{row} PSNR / col. dev." for row in rows) + " |",
             "|---|" + "---:|" * len(rows)]
    for scene in scenes:
        cells = []
        for row in rows:
            rec = next((r for r in records if r["scene"] == scene and r["row"] == row and "error" not in r), None)
            cells.append("—" if rec is None else f"{_fmt(rec['novel_psnr'], 2)} / {_fmt(rec['colour_deviation'], 4)}")
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def error_time_markdown(records: list[dict[str, Any]]) -> str:
    lines = ["| schedule | stage end | wall time (s) | novel PSNR (dB) ↑ | Chamfer ↓ | F-score ↑ | scenes |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for label in dict.fromkeys(r["schedule"] for r in records):
        ok = [r for r in records if r["schedule"] == label and "error" not in r]
        for i, stage in enumerate(POINTS):
            pts = [r["points"][i] for r in ok]
            if not pts:
                continue
            mean = {k: sum(p[k] for p in pts) / len(pts) for k in ("wall_s", "novel_psnr", "chamfer", "fscore")}
            lines.append(f"| {label} | {stage} | {mean['wall_s']:.1f} | {mean['novel_psnr']:.2f} | "
                         f"{mean['chamfer']:.4f} | {mean['fscore']:.3f} | {len(pts)} |")
    failed = [r for r in records if "error" in r]
    if failed:
        lines += ["", "Failed: " + "; ".join(f"{r['schedule']}/{r['scene']}: {r['error']}" for r in failed)]
    return "\n".join(lines) + "\n"


def stability_markdown(records: list[dict[str, Any]]) -> str:
    lines = ["| setting | finished | guard events | finite outputs | ref. PSNR GLB (dB) | novel PSNR (dB) | "
             "colour dev. | Chamfer | error |", "|---|---|---:|---|---:|---:|---:|---:|---|"]
    for r in records:
        lines.append(f"| {r['entry']} | {'yes' if r['finished'] else 'NO'} | {r['guard_events']} | "
                     f"{'yes' if r.get('finite_outputs') else 'NO' if r['finished'] else '—'} | "
                     f"{_fmt(r.get('ref_psnr_glb'), 2)} | {_fmt(r.get('novel_psnr'), 2)} | "
                     f"{_fmt(r.get('colour_deviation'), 4)} | {_fmt(r.get('chamfer'), 4)} | {r.get('error') or ''} |")
    return "\n".join(lines) + "\n"


def plot_error_time(records: list[dict[str, Any]], path: Path, title: str) -> Path:
    """Novel PSNR and Chamfer against cumulative wall time, one curve per schedule (scene mean),
    plus the reference-PSNR curves from the stage logs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    labels = list(dict.fromkeys(r["schedule"] for r in records))
    for colour, label in enumerate(labels):
        ok = [r for r in records if r["schedule"] == label and "error" not in r]
        if not ok:
            continue
        xs = [sum(r["points"][i]["wall_s"] for r in ok) / len(ok) for i in range(len(POINTS))]
        for ax, key in ((axes[0], "novel_psnr"), (axes[1], "chamfer")):
            ys = [sum(r["points"][i][key] for r in ok) / len(ok) for i in range(len(POINTS))]
            ax.plot(xs, ys, marker="o", label=label, color=f"C{colour}")
            for x, y, stage in zip(xs, ys, POINTS, strict=True):
                ax.annotate(stage.split("_")[0], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        for stage, point in zip(POINTS, ok[0]["points"], strict=True):
            curve = ok[0]["curves"].get(stage, [])
            if curve:  # the log's clock starts with the stage, which ends at the point's time
                start = point["wall_s"] - curve[-1][0]
                axes[2].plot([start + t for t, _ in curve], [p for _, p in curve], color=f"C{colour}")
    axes[0].set(xlabel="wall time (s)", ylabel="novel-view PSNR vs truth (dB)", xscale="log")
    axes[1].set(xlabel="wall time (s)", ylabel="Chamfer distance", xscale="log")
    axes[2].set(xlabel="wall time (s)", ylabel="reference-view PSNR (stage logs, first scene)", xscale="log")
    axes[0].legend()
    fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    plt.close(fig)
    return path
