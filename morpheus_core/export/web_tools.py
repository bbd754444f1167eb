"""Where the Node tools of the export live: ``tools/web`` of the repository (``make web-tools`` runs ``npm ci``
there), or the folder ``MORPHEUS_WEB_TOOLS`` names (a ``tools/web`` installed elsewhere). The glTF validator, the
viewer's ``<model-viewer>`` and the meshopt decoder are all found through ``web_tool``."""

from __future__ import annotations

import os
from pathlib import Path

WEB_TOOLS_ENV = "MORPHEUS_WEB_TOOLS"
REPO_WEB_TOOLS = Path(__file__).resolve().parents[2] / "tools" / "web"


def web_tools_dir() -> Path:
    """The folder holding ``package.json`` and ``node_modules`` of the Node tools."""
    override = os.environ.get(WEB_TOOLS_ENV)
    return Path(override) if override else REPO_WEB_TOOLS


def web_tool(relative: str) -> Path:
    """``node_modules/<relative>`` of the web tools; ``FileNotFoundError`` saying how to install it when absent."""
    path = web_tools_dir() / "node_modules" / relative
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: run `make web-tools` (npm ci --prefix {web_tools_dir()}; "
                                f"needs Node.js and npm), or point {WEB_TOOLS_ENV} at an installed tools/web")
    return path
