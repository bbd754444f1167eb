"""Reading the catalog report's HTML in tests: the numbers that must not change when work is counted once."""

from __future__ import annotations

import re


def totals(page: str) -> dict[str, object]:
    """What must not change when a run finds everything cached: the wall-time table, the histograms and
    the asset rows' metrics, the photos and the runs that did work."""
    def fact(name: str) -> int:
        m = re.search(rf"<td>{re.escape(name)}</td><td>(\d+)</td>", page)
        assert m, name
        return int(m.group(1))

    walltime = re.search(r'<table class="walltime">.*?</table>', page)
    assets = re.findall(r'<tr class="asset" data-photo-key="([^"]*)">(.*?)</tr>', page)
    return {"walltime": walltime.group(0) if walltime else None, "photos": fact("photos"),
            "runs": fact("runs that did work"), "histograms": re.findall(r"<figcaption>([^<]*)</figcaption>", page),
            "assets": [(k, re.findall(r"<td>(.*?)</td>", cells)[:-1]) for k, cells in assets]}
