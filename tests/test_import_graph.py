"""The package's imports run one way: model and math, blocks, wiring, studies, CLI.

Parsed with ``ast`` from the sources (imports inside functions included; those
under ``if TYPE_CHECKING:`` are annotations only and are skipped; relative
imports resolved against the importing module), so the test needs no import
side effects. ``from package import name`` imports the
package (its ``__init__`` runs and is read for ``name``), and the submodule
too when ``name`` is one.
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
        "limits",
        "contracts",
        "drake_typing",
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
        "update_laws",
        "points",
        "sector",
        "observer",
        "observer_certificate",
        "interval",
        "interval_linalg",
        "interval_taylor",
        "branch_and_bound",
        "multibody_bounds",
        "symbolic_bounds",
        "domain",
        "jacobian_bounds",
        "lmi",
        "structured_lmi",
        "design",  # the subpackage; inside it, see test_the_design_package_has_no_import_cycle
        "baselines",
        "verification",
        "unobservable",
        "validity",
        "provenance",
        "learning",
        "model_error",
    },
    1: {"systems"},  # Drake blocks, thin wrappers over the math
    2: {"variants", "slots", "scenario", "diagram"},  # wiring
    3: {  # studies and what presents them
        "simulation",
        "guard",  # the Simulator monitor of simulate
        "progress",  # the progress bar of runs and sweeps
        "sweep",  # the parallel runs of ablate and montecarlo
        "sweep_store",  # and their results on disk
        "ablation",
        "ablation_grid",
        "ablation_tasks",
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


def _absolute(node: ast.ImportFrom, package: str) -> str | None:
    """The module that ``from ... import`` names, a relative one resolved against ``package``.

    ``package`` is the ofrl_drake package of the importing module (``""`` for
    the top level, ``"design"`` for ``design.driver`` and ``design/__init__``):
    ``from .sdp import x`` there is ``ofrl_drake.design.sdp``, ``from .. import
    diagram`` is ``ofrl_drake``.
    """
    if node.level == 0:
        return node.module
    parts = ["ofrl_drake", *filter(None, package.split("."))]
    if node.level > len(parts):
        raise AssertionError(
            f"a relative import of level {node.level} in ofrl_drake.{package or '__init__'} "
            "reaches above the package"
        )
    base = parts[: len(parts) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(tree: ast.AST, modules: set[str], package: str = "") -> set[str]:
    """The ofrl_drake modules that the source ``tree`` imports at run time.

    ``package`` is the package of the module ``tree`` is the source of, for its
    relative imports (:func:`_absolute`).
    """
    skipped = _type_checking_nodes(tree)
    targets: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.ImportFrom):
            name = _absolute(node, package)
            if name and (name == "ofrl_drake" or name.startswith("ofrl_drake.")):
                base = _resolve(name, modules)
                targets.add(base)  # its __init__ runs, and is read for the names
                for alias in node.names:  # "from pkg import submodule" imports that too
                    sub = f"{name}.{alias.name}".removeprefix("ofrl_drake.")
                    if sub in modules:
                        targets.add(sub)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("ofrl_drake"):
                    targets.add(_resolve(alias.name, modules))
    return targets


def import_graph() -> dict[str, set[str]]:
    """Module -> the ofrl_drake modules it imports at run time."""
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    modules = set(files)
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        graph[module] = imports_of(tree, modules, package) - {module}
    return graph


def circles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """The import circles of ``graph``: its strongly connected components of two or more.

    Tarjan's algorithm, iterative (no recursion limit on long chains).
    """
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: set[frozenset[str]] = set()
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.add(frozenset(component))
    return found


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


#: Import circles tolerated: none. Nothing may be added to it.
KNOWN_CIRCLES: set[frozenset[str]] = set()


def test_the_package_has_no_import_circle():
    """No strongly connected component of the module graph (lazy imports included)."""
    found = circles(GRAPH)
    new = sorted(" <-> ".join(sorted(c)) for c in found - KNOWN_CIRCLES)
    gone = sorted(" <-> ".join(sorted(c)) for c in KNOWN_CIRCLES - found)
    assert not new, f"import circles: {'; '.join(new)}"
    assert not gone, f"no longer circles, remove them from KNOWN_CIRCLES: {'; '.join(gone)}"


def test_circles_finds_every_strongly_connected_component():
    graph = {
        "a": {"b"},
        "b": {"c"},
        "c": {"a", "d"},
        "d": {"e"},
        "e": {"d"},
        "f": {"a"},
        "g": set(),
    }
    assert circles(graph) == {frozenset("abc"), frozenset("de")}
    chain = {str(i): {str(i + 1)} for i in range(5000)} | {"5000": {"0"}}
    assert circles(chain) == {frozenset(chain)}  # no recursion limit
    assert circles({"a": {"b"}, "b": set()}) == set()


def test_from_a_package_import_reads_the_package():
    modules = {"examples", "examples.two_state", "systems", "systems.world", ""}
    targets = imports_of(ast.parse("from ofrl_drake.examples import two_state"), modules)
    assert targets == {"examples", "examples.two_state"}
    targets = imports_of(ast.parse("from ofrl_drake.systems.world import MeasuredPlant"), modules)
    assert targets == {"systems.world"}
    lazy = "def f():\n    from ofrl_drake.examples import make_system\n"
    assert imports_of(ast.parse(lazy), modules) == {"examples"}
    hidden = "if TYPE_CHECKING:\n    from ofrl_drake.systems import world\n"
    assert imports_of(ast.parse(hidden), modules) == set()


def test_relative_imports_are_resolved_against_the_importing_module():
    modules = {"", "diagram", "systems", "systems.world", "systems.critic", "design"}
    modules |= {"design.sdp", "design.driver"}

    def targets(source, package):
        return imports_of(ast.parse(source), modules, package)

    # In systems/critic.py (package "systems"), and in systems/__init__.py (likewise).
    assert targets("from .world import MeasuredPlant", "systems") == {"systems.world"}
    assert targets("from . import world", "systems") == {"systems", "systems.world"}
    assert targets("from ..diagram import SIGNALS", "systems") == {"diagram"}
    assert targets("from .. import diagram", "systems") == {"", "diagram"}
    assert targets("def f():\n    from ..design import sdp\n", "systems") == {
        "design",
        "design.sdp",
    }
    # In a top-level module (package ""): its siblings.
    assert targets("from .diagram import SIGNALS", "") == {"diagram"}
    assert targets("if TYPE_CHECKING:\n    from .diagram import SIGNALS\n", "") == set()
    with pytest.raises(AssertionError, match=r"level 3 in ofrl_drake\.systems reaches above"):
        targets("from ...elsewhere import x", "systems")


def _import_order(modules: set[str]) -> list[str]:
    """``modules`` ordered so that each imports only those before it; fails on a cycle."""
    edges = {m: GRAPH[m] & modules for m in modules}
    order: list[str] = []
    while edges:
        free = sorted(m for m, deps in edges.items() if not deps - set(order))
        assert free, f"import cycle among {sorted(edges)}"
        order.extend(free)
        for m in free:
            del edges[m]
    return order


def test_the_wiring_runs_one_way():
    """variants (the factories) -> slots (the registry) -> scenario -> diagram."""
    order = _import_order({m for m in GRAPH if _layer(m) == 2})
    assert order.index("variants") < order.index("slots") < order.index("scenario")
    assert order.index("scenario") < order.index("diagram")


def test_the_design_package_has_no_import_cycle():
    """Problem data -> formulations -> backends -> result -> driver, none importing back."""
    order = _import_order({m for m in GRAPH if m == "design" or m.startswith("design.")})
    steps = ["design.sdp", "design.formulations", "design.backends", "design.result"]
    steps += ["design.driver", "design.rate", "design"]
    assert [order.index(m) for m in steps] == sorted(order.index(m) for m in steps)
    assert "design.pipeline" in GRAPH["design.result"]  # from_gains solves through it


def test_the_graph_sees_the_imports_it_must_see():
    """The parser finds function-local imports and skips TYPE_CHECKING ones."""
    assert "slots" in GRAPH["scenario"]  # imported inside validate_scenario
    assert "design" in GRAPH["systems.scheduled_observer"]  # inside _resolve
    assert "slots" not in GRAPH["variants"]  # only under TYPE_CHECKING
    assert "diagram" not in GRAPH["slots"] and "scenario" not in GRAPH["slots"]
    assert "observer_certificate" in GRAPH["simulation"]
    assert "examples.two_state" in GRAPH["examples.coupled_two_state"]


def test_every_public_name_resolves_and_every_error_is_the_projects():
    """``ofrl_drake.__all__`` names what ``ofrl_drake`` gives, and a user catches every
    documented refusal of ``simulate`` / ``build_closed_loop`` with ``od.OfrlError``."""
    import ofrl_drake as od

    for name in od.__all__:
        assert getattr(od, name) is not None, name
    errors = [getattr(od, n) for n in od.__all__ if n.endswith(("Error", "Infeasible", "Exceeded"))]
    assert {e.__name__ for e in errors} >= {
        "AblationError",
        "DesignError",
        "ModelError",
        "MonteCarloError",
        "ObserverDesignInfeasible",
        "ScenarioError",
        "SwapError",
        "WallTimeExceeded",
    }
    assert all(issubclass(e, od.OfrlError) for e in errors)
