"""The Dagster UI shows the pipeline's asset graph.

``dagster-webserver`` serves the repository's real ``workspace.yaml`` on a loopback port; headless Chromium
(selenium driving the Debian ``chromium``/``chromium-driver`` packages) renders the global asset lineage page, and
the asset nodes and lineage edges read back from the rendered SVG must be those of
``orchestration.definitions.defs``. The UI draws an edge as a bare ``<path>`` (no ids or data attributes naming its
ends), so each edge is identified geometrically: its first point lies on the source node's ``<foreignObject>``
box, its last point (under the arrow head) just outside the target's.

Skips only when Chromium, chromedriver or selenium are missing (``make browser``, a dependency of ``make test``,
installs the Debian packages). The screenshot goes to ``benchmarks/results/dagster_asset_graph.png`` when the
file does not exist yet or ``MORPHEUS_UPDATE_SCREENSHOT=1``; otherwise to pytest's tmp dir.
"""

from __future__ import annotations

import math
import time
import urllib.parse
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.browser import chromium, needs_browser
from tests.dagster_ui import RENDER_TIMEOUT_S, VIEWPORT, save_screenshot, serve, write_instance_config

# The pipeline's assets: the graph must show at least these (so an empty graph cannot pass).
PIPELINE_ASSETS = ("reference", "nerf", "dmtet", "texture", "bake", "export", "qa")
# "Lineage" in the UI's navigation: the global asset lineage graph, every asset of every code location. With more
# than one asset group the UI collapses each group into one box unless it is listed in ``?expanded=`` (as
# ``global@global:<group>`` while the UI's per-code-location grouping flag is off, its default).
GRAPH_PATH = "/asset-groups"
# An edge's ends are on (start) or a few units outside (end, under the arrow) its nodes' boxes; the gap between
# two ranks of the layout is ~60 units.
ENDPOINT_TOLERANCE = 25.0


pytestmark = needs_browser


# ---------------------------------------------------------------- expected graph, from the Definitions object


def _display_name(key) -> str:
    """The UI labels a graph node with the last component of its asset key."""
    return key.path[-1]


@dataclass(frozen=True)
class Expected:
    names: set[str]  # node labels
    edges: set[tuple[str, str]]  # (upstream, downstream)
    groups: set[str]


def expected_graph() -> Expected:
    """Every asset of ``orchestration.definitions.defs`` with its dependencies, as the UI should draw them."""
    from orchestration.definitions import defs

    graph = defs.resolve_asset_graph()
    keys = set(graph.get_all_asset_keys())
    names = {_display_name(key) for key in keys}
    assert len(names) == len(keys), f"asset keys share a last component, the UI labels would be ambiguous: {keys}"
    edges = {
        (_display_name(parent), _display_name(key))
        for key in keys
        for parent in graph.get(key).parent_keys
        if parent in keys and parent != key
    }
    return Expected(names, edges, groups={graph.get(key).group_name for key in keys})


@pytest.fixture
def expected() -> Expected:
    """Checked before the webserver starts: the definitions must hold the pipeline's assets."""
    graph = expected_graph()
    missing = sorted(set(PIPELINE_ASSETS) - graph.names)
    assert not missing, f"orchestration.definitions.defs lacks pipeline assets {missing} (has {sorted(graph.names)})"
    return graph


def graph_url(base: str, groups: set[str]) -> str:
    expanded = ",".join(f"global@global:{group}" for group in sorted(groups))
    return f"{base}{GRAPH_PATH}?{urllib.parse.urlencode({'expanded': expanded})}"


@pytest.fixture
def webserver(tmp_path: Path) -> Iterator[str]:
    """The repository's code location with its default settings over an empty instance."""
    home = tmp_path / "dagster_home"
    write_instance_config(home)
    with serve(home, tmp_path / "webserver.log") as base:
        yield base


# ---------------------------------------------------------------- the browser


@pytest.fixture
def browser() -> Iterator:
    with chromium(VIEWPORT) as driver:
        yield driver


# The graph's <svg> (the one holding <foreignObject> nodes): each node's box in SVG units and its own texts (an
# element's direct text, plus data-tooltip, which carries the untruncated name of a full-size node); each edge
# <path> (outside <defs> and nodes) by its first and last points.
SNAPSHOT_JS = """
const svg = Array.from(document.querySelectorAll('svg')).find((s) => s.querySelector('foreignObject'));
if (!svg) { return null; }
const num = (el, name) => parseFloat(el.getAttribute(name));
const nodes = Array.from(svg.querySelectorAll('foreignObject'))
  .filter((fo) => !fo.classList.contains('group'))
  .map((fo) => {
    const texts = new Set();
    for (const el of fo.querySelectorAll('*')) {
      if (el.dataset && el.dataset.tooltip) { texts.add(el.dataset.tooltip.trim()); }
      const own = Array.from(el.childNodes).filter((n) => n.nodeType === 3).map((n) => n.textContent).join('');
      if (own.trim()) { texts.add(own.trim()); }
    }
    return {x: num(fo, 'x'), y: num(fo, 'y'), w: num(fo, 'width'), h: num(fo, 'height'), texts: Array.from(texts)};
  });
const edges = Array.from(svg.querySelectorAll('path'))
  .filter((p) => !p.closest('defs, marker, foreignObject'))
  .map((p) => {
    const a = p.getPointAtLength(0);
    const b = p.getPointAtLength(p.getTotalLength());
    return {x1: a.x, y1: a.y, x2: b.x, y2: b.y, d: p.getAttribute('d')};
  });
return {nodes: nodes, edges: edges};
"""


@dataclass
class Box:
    x: float
    y: float
    w: float
    h: float

    def distance(self, px: float, py: float) -> float:
        dx = max(self.x - px, 0.0, px - (self.x + self.w))
        dy = max(self.y - py, 0.0, py - (self.y + self.h))
        return math.hypot(dx, dy)


def _label_matches(label: str, name: str) -> bool:
    """The UI middle-truncates long names with an ellipsis (``refined_…ture``)."""
    if label == name:
        return True
    head, sep, tail = label.partition("…")
    return bool(sep) and len(name) > len(head) + len(tail) and name.startswith(head) and name.endswith(tail)


@dataclass
class Rendered:
    nodes: dict[str, Box]  # asset name -> node box
    edges: set[tuple[str, str]]  # (upstream, downstream), from the paths' endpoints
    unattached: list[str]  # paths whose ends are not on two asset nodes
    ambiguous: list[str]  # node boxes whose texts match several asset names


def read_graph(snapshot: dict | None, names: set[str]) -> Rendered:
    rendered = Rendered(nodes={}, edges=set(), unattached=[], ambiguous=[])
    if not snapshot:
        return rendered
    for node in snapshot["nodes"]:
        matches = {name for name in names for label in node["texts"] if _label_matches(label, name)}
        if len(matches) == 1:
            rendered.nodes[matches.pop()] = Box(node["x"], node["y"], node["w"], node["h"])
        elif matches:
            rendered.ambiguous.append(f"{sorted(matches)} at ({node['x']}, {node['y']})")

    def nearest(px: float, py: float) -> str | None:
        if not rendered.nodes:
            return None
        name, box = min(rendered.nodes.items(), key=lambda item: item[1].distance(px, py))
        return name if box.distance(px, py) <= ENDPOINT_TOLERANCE else None

    for edge in snapshot["edges"]:
        upstream, downstream = nearest(edge["x1"], edge["y1"]), nearest(edge["x2"], edge["y2"])
        if upstream and downstream and upstream != downstream:
            rendered.edges.add((upstream, downstream))
        else:
            rendered.unattached.append(f"{edge['d']} ({upstream} -> {downstream})")
    return rendered


# ---------------------------------------------------------------- the test


def test_ui_shows_asset_graph(expected: Expected, webserver: str, browser, tmp_path: Path) -> None:
    names, edges = expected.names, expected.edges
    started = time.monotonic()
    browser.get(graph_url(webserver, expected.groups))
    deadline = time.monotonic() + RENDER_TIMEOUT_S
    while True:
        rendered = read_graph(browser.execute_script(SNAPSHOT_JS), names)
        done = names <= rendered.nodes.keys() and rendered.edges == edges and not rendered.unattached
        if done or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    if done:
        time.sleep(1.0)  # let the nodes' status colours (a separate query) arrive before the screenshot
    shot = save_screenshot(browser, tmp_path, rendered_ok=done)
    print(f"asset graph rendered in {time.monotonic() - started:.1f} s; screenshot {shot}")

    where = f"(page {browser.current_url!r}, title {browser.title!r}, screenshot {shot})"
    assert not rendered.ambiguous, f"nodes with several asset names: {rendered.ambiguous} {where}"
    assert names <= rendered.nodes.keys(), f"asset nodes not shown: {sorted(names - rendered.nodes.keys())} {where}"
    assert not rendered.unattached, f"edges not joining two asset nodes: {rendered.unattached} {where}"
    assert rendered.edges == edges, (
        f"lineage edges differ from the definitions: missing {sorted(edges - rendered.edges)}, "
        f"unexpected {sorted(rendered.edges - edges)} {where}"
    )

