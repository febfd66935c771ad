"""The package's imports run one way: model and math, blocks, wiring, studies, CLI.

Parsed with ``ast`` from the sources (imports inside functions included; those
under ``if TYPE_CHECKING:`` are annotations only and are skipped), so the test
needs no import side effects.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "ofrl_drake"

#: Layer of each module, bottom up. ``examples.*`` are models (0), ``systems.*`` blocks (1).
LAYERS = {
    0: {  # model and math: plain numpy (and Drake's math), no blocks
        "errors",
        "_jit",
        "checks",
        "atomic",
        "model",
        "plants",
        "drake_models",
        "expression_function",
        "examples",
        "basis",
        "cost",
        "policy",
        "bellman",
        "points",
        "sector",
        "observer",
        "observer_certificate",
        "interval",
        "jacobian_bounds",
        "lmi",
        "structured_lmi",
        "design",
        "structured_design",
        "design_cvxpy",
        "baselines",
        "verification",
        "unobservable",
        "validity",
        "guard",
        "provenance",
        "learning",
        "sweep",
        "model_error",
    },
    1: {"systems"},  # Drake blocks, thin wrappers over the math
    2: {"variants", "scenario", "diagram"},  # wiring
    3: {  # studies and what presents them
        "simulation",
        "ablation",
        "ablation_metrics",
        "ablation_report",
        "optimal",
        "plotting",
        "graph",
        "animation",
        "learning_curve",
        "monte_carlo",
    },
    4: {"cli", "__main__", ""},  # the command line and the package's public face
}
NAMES = {0: "model/math", 1: "blocks", 2: "wiring", 3: "studies", 4: "CLI"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _layer(module: str) -> int:
    head = module.split(".")[0]
    for layer, names in LAYERS.items():
        if head in names or module in names:
            return layer
    raise AssertionError(
        f"ofrl_drake.{module} has no layer: add it to LAYERS in tests/test_import_graph.py"
    )


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                skipped.update(id(sub) for sub in ast.walk(child))
    return skipped


def _resolve(target: str, modules: set[str]) -> str:
    """``ofrl_drake.a.b`` -> the module ``a.b`` (or its package ``a``)."""
    name = target.removeprefix("ofrl_drake").lstrip(".")
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name


def import_graph() -> dict[str, set[str]]:
    """Module -> the ofrl_drake modules it imports at run time."""
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    modules = set(files)
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        skipped = _type_checking_nodes(tree)
        targets: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in skipped:
                continue
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module == "ofrl_drake" or node.module.startswith("ofrl_drake."):
                    base = node.module
                    for alias in node.names:  # "from pkg import submodule"
                        sub = f"{base}.{alias.name}"
                        hit = _resolve(sub, modules)
                        targets.add(
                            hit
                            if hit == sub.removeprefix("ofrl_drake.")
                            else _resolve(base, modules)
                        )
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith("ofrl_drake"):
                        targets.add(_resolve(alias.name, modules))
        targets.discard(module)
        graph[module] = targets
    return graph


GRAPH = import_graph()


def test_every_module_has_a_layer():
    for module in GRAPH:
        _layer(module)


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_imports_only_go_down_the_layers(module):
    mine = _layer(module)
    upward = sorted(t for t in GRAPH[module] if _layer(t) > mine)
    assert not upward, f"ofrl_drake.{module or '__init__'} ({NAMES[mine]}) imports " + ", ".join(
        f"{t} ({NAMES[_layer(t)]})" for t in upward
    )


def test_the_wiring_has_no_import_cycle():
    """scenario -> variants and diagram -> scenario, variants: no way back."""
    wiring = {m for m in GRAPH if _layer(m) == 2}
    edges = {m: GRAPH[m] & wiring for m in wiring}
    order: list[str] = []
    while edges:
        free = sorted(m for m, deps in edges.items() if not deps - set(order))
        assert free, f"import cycle among {sorted(edges)}"
        order.extend(free)
        for m in free:
            del edges[m]
    assert order.index("variants") < order.index("scenario") < order.index("diagram")


def test_the_graph_sees_the_imports_it_must_see():
    """The parser finds function-local imports and skips TYPE_CHECKING ones."""
    assert "variants" in GRAPH["scenario"]  # imported inside validate_scenario
    assert "design" in GRAPH["systems.scheduled_observer"]  # inside _resolve
    assert "diagram" not in GRAPH["variants"]  # only under TYPE_CHECKING
    assert "observer_certificate" in GRAPH["simulation"]
    assert "examples.two_state" in GRAPH["examples.coupled_two_state"]
