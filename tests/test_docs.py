"""docs/architecture.md's module table lists every module of the package, once, in its layer.

A module without a row, or a row naming a module that does not exist, fails with the
exact rows to add or remove; the layer column follows tests/test_import_graph.py.
"""

import ast
import re
from pathlib import Path

from .conftest import ROOT
from .test_import_graph import NAMES, _layer

PAGE = ROOT / "docs" / "architecture.md"
PACKAGE = ROOT / "ofrl_drake"


def package_modules() -> list[str]:
    """Every module file of the package, as ``ofrl_drake/...py`` from the repository root."""
    return sorted(
        p.relative_to(ROOT).as_posix()
        for p in PACKAGE.rglob("*.py")
        if "__pycache__" not in p.parts
    )


def layer_name(module: str) -> str:
    """The layer tests/test_import_graph.py gives ``ofrl_drake/a/b.py`` (``a.b``)."""
    parts = Path(module).relative_to("ofrl_drake").with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    try:
        return NAMES[_layer(".".join(parts))]
    except AssertionError:
        return "no layer (add the module to LAYERS in tests/test_import_graph.py)"


def table_rows(text: str) -> list[tuple[str, str, str]]:
    """(module, layer, role) of each row of the table under ``## Modules``."""
    section = text.split("\n## Modules\n", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(
        r"^\| `(ofrl_drake/[^`]+)` \| ([^|]+?) \| (.+?) \|$", section, flags=re.MULTILINE
    )
    assert rows, "no module table under '## Modules' in docs/architecture.md"
    return rows


def _role(module: str) -> str:
    """A draft role for a missing row: the first line of the module's docstring."""
    path = ROOT / module
    doc = ast.get_docstring(ast.parse(path.read_text())) if path.is_file() else None
    return (doc or "ROLE").splitlines()[0].rstrip(".")


def problems(rows, modules, layer_of=layer_name) -> list[str]:
    """What to change in the table so that it lists ``modules``, each once, in its layer."""
    listed = [m for m, _, _ in rows]
    found = [
        f"remove one of the rows of `{m}`: it is listed twice"
        for m in sorted({m for m in listed if listed.count(m) > 1})
    ]
    found += [
        f"add the row | `{m}` | {layer_of(m)} | {_role(m)} |" for m in modules if m not in listed
    ]
    found += [f"remove the row of `{m}`: no such module" for m in listed if m not in modules]
    found += [
        f"row of `{m}`: the layer is {layer_of(m)}, not {layer}"
        for m, layer, _ in rows
        if m in modules and layer != layer_of(m)
    ]
    return found


def test_the_architecture_table_lists_every_module_once_in_its_layer():
    found = problems(table_rows(PAGE.read_text()), package_modules())
    assert not found, "docs/architecture.md, '## Modules':\n" + "\n".join(found)


def test_every_row_has_a_role():
    assert [m for m, _, role in table_rows(PAGE.read_text()) if not role.strip()] == []


def test_a_missing_an_extra_a_repeated_row_and_a_wrong_layer_are_seen():
    rows, modules = table_rows(PAGE.read_text()), package_modules()
    model = next(r for r in rows if r[0] == "ofrl_drake/model.py")
    without = [r for r in rows if r is not model]
    assert problems(without, modules) == [
        "add the row | `ofrl_drake/model.py` | model/math | "
        "The control-affine plant model ``x' = f(x) + g(x) u``, ``y = C x`` |"
    ]
    gone = ("ofrl_drake/gone.py", "studies", "a module split away")
    assert problems([*rows, gone], modules) == [
        "remove the row of `ofrl_drake/gone.py`: no such module"
    ]
    assert problems([*rows, model], modules) == [
        "remove one of the rows of `ofrl_drake/model.py`: it is listed twice"
    ]
    moved = [(m, "studies" if m == model[0] else layer, role) for m, layer, role in rows]
    assert problems(moved, modules) == [
        "row of `ofrl_drake/model.py`: the layer is model/math, not studies"
    ]


def test_every_module_file_is_seen():
    modules = package_modules()
    assert "ofrl_drake/__init__.py" in modules
    assert "ofrl_drake/systems/plant.py" in modules
    assert "ofrl_drake/examples/two_state.py" in modules
    assert layer_name("ofrl_drake/systems/plant.py") == "blocks"
    assert layer_name("ofrl_drake/examples/two_state.py") == "model/math"
    assert layer_name("ofrl_drake/__init__.py") == "CLI"
    assert layer_name("ofrl_drake/not_in_layers.py").startswith("no layer")
