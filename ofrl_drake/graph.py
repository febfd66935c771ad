"""Draw a Drake diagram with Graphviz (``dot``)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from pydrake.systems.framework import Diagram

__all__ = ["diagram_dot", "diagram_svg", "dot_available", "render_diagram"]


def diagram_dot(diagram: Diagram, max_depth: int = 1) -> str:
    """The Graphviz source of ``diagram`` (``GetGraphvizString``)."""
    return diagram.GetGraphvizString(max_depth=max_depth)


def dot_available() -> bool:
    """True if Graphviz's ``dot`` is on the PATH."""
    return shutil.which("dot") is not None


def render_diagram(diagram: Diagram, directory: str | Path, stem: str = "diagram") -> Path:
    """Write ``<stem>.svg`` rendered with ``dot``, or ``<stem>.dot`` if ``dot`` is missing.

    Returns the path written; check its suffix to know which.
    """
    directory = Path(directory)
    source = diagram_dot(diagram)
    if not dot_available():
        path = directory / f"{stem}.dot"
        path.write_text(source)
        return path
    path = directory / f"{stem}.svg"
    svg = subprocess.run(
        ["dot", "-Tsvg"], input=source.encode(), capture_output=True, check=True
    ).stdout
    path.write_bytes(svg)
    return path


def diagram_svg(diagram: Diagram) -> str:
    """The diagram rendered as an SVG string (for notebooks); needs ``dot``."""
    if not dot_available():
        raise RuntimeError(
            "Graphviz 'dot' is not installed; install it with `apt-get install -y graphviz`."
        )
    return subprocess.run(
        ["dot", "-Tsvg"], input=diagram_dot(diagram).encode(), capture_output=True, check=True
    ).stdout.decode()
