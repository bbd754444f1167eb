"""Two settings' stage step times compared over several device calls, in both run orders.

On the H200 one call's ratio can mix the change with the run order: in the VAE precision calls the
second ``paper_speed.py`` run read faster in 11 of 12 rows, whichever setting it ran
(``benchmarks/results/vae_precision_h200.md``). Each ``--pair`` is one call's reference and change
tables (``paper_speed.py`` JSON) and which of them ran first. The summary's ratio is the geometric mean
over the pairs, so a pair in each order cancels a constant order effect; each pair's ratio is shown.

    python -m benchmarks.speed_ab --pair REF.json NEW.json ref --pair REF.json NEW.json new \\
        --name vae_precision_h200 --title "..." --about "..."
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from benchmarks.quality import _write

RESULTS = Path(__file__).resolve().parent / "results"


def object_step_ms(table: dict[str, Any]) -> dict[tuple[str, int], float]:
    return {(r["stage"], int(r["batch"])): float(r["ms_per_step"]) / int(r["batch"]) for r in table["rows"]}


def compare(pairs: list[tuple[dict[str, Any], dict[str, Any], str]]) -> list[dict[str, Any]]:
    """Per stage and batch present in every pair: each pair's ms per object-step (ref, new), its
    ratio new / ref, and the geometric mean of the ratios."""
    per_pair = [(object_step_ms(ref), object_step_ms(new), first) for ref, new, first in pairs]
    keys = set.intersection(*(set(r) & set(n) for r, n, _ in per_pair))
    stages = {"nerf": 0, "dmtet": 1, "texture": 2}
    rows = []
    for stage, batch in sorted(keys, key=lambda k: (stages.get(k[0], 9), k[1])):
        cells = [{"first": first, "ref_ms": round(r[(stage, batch)], 1), "new_ms": round(n[(stage, batch)], 1),
                  "ratio": n[(stage, batch)] / r[(stage, batch)]} for r, n, first in per_pair]
        geo = math.exp(sum(math.log(c["ratio"]) for c in cells) / len(cells))
        rows.append({"stage": stage, "batch": batch, "pairs": cells, "ratio": round(geo, 3),
                     "orders": sorted({c["first"] for c in cells})})
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    firsts = [c["first"] for c in rows[0]["pairs"]]
    head = " | ".join(f"pair {i + 1} ({f} first): ref → new ms" for i, f in enumerate(firsts))
    lines = ["ms per object-step (ms per step / batch); ratio = geometric mean of new / ref over the pairs.", "",
             f"| stage | batch | {head} | ratio new / ref | change |",
             "|---|---:|" + "---:|" * len(firsts) + "---:|---:|"]
    for r in rows:
        cells = " | ".join(f"{c['ref_ms']} → {c['new_ms']} ({c['ratio'] - 1:+.0%})" for c in r["pairs"])
        lines.append(f"| {r['stage']} | {r['batch']} | {cells} | {r['ratio']:.3f} | {r['ratio'] - 1:+.0%} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pair", nargs=3, action="append", required=True, metavar=("REF", "NEW", "FIRST"),
                    help="one call's paper_speed JSON for the reference and the change, and which ran first")
    ap.add_argument("--name", required=True, help="results file stem")
    ap.add_argument("--title", default="Stage step times, reference against change")
    ap.add_argument("--about", default="")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    pairs = []
    for ref, new, first in args.pair:
        if first not in ("ref", "new"):
            ap.error(f"FIRST must be ref or new, got {first!r}")
        pairs.append((json.loads(Path(ref).read_text()), json.loads(Path(new).read_text()), first))
    rows = compare(pairs)
    if not rows:
        ap.error("the tables share no (stage, batch) row")
    first = pairs[0][0]
    payload = {"title": args.title, "about": args.about, "machine": f"{first['device']}, torch {first['torch']}",
               "date": first["date"], "wall_s": 0.0, "rows": rows,
               "command": "python -m benchmarks.speed_ab " + " ".join(
                   " ".join(["--pair", *(Path(p).name for p in pair[:2]), pair[2]]) for pair in args.pair)}
    _write(args.results, args.name, payload, markdown(rows))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
