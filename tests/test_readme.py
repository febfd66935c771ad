"""The README: its scenario-key table stays in sync with the scenario dataclasses, and its
Python example runs."""

import dataclasses
import re
import subprocess
import sys
import types
import typing

from ofrl_drake.scenario import Scenario

from .conftest import ROOT

#: How the table spells each field type.
TYPE_NAMES = {
    float: "number",
    int: "integer",
    str: "string",
    list[float]: "vector",
    list[int]: "list of integers",
    list[list[float]]: "matrix",
    dict[str, float]: "mapping of numbers",
}

#: Keys whose "required" column says more than yes/no.
EITHER = {"system", "plant"}


def _strip_optional(tp):
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return next(a for a in typing.get_args(tp) if a is not type(None))
    return tp


def schema_keys(schema=Scenario, prefix=""):
    """(key path, type name, required) for every key the loader accepts."""
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        tp = _strip_optional(hints[f.name])
        required = not f.metadata.get("optional", False)
        key = prefix + f.name
        if dataclasses.is_dataclass(tp):
            yield key, "mapping", required
            yield from schema_keys(tp, key + ".")
        else:
            yield key, TYPE_NAMES[tp], required


def readme_keys():
    text = (ROOT / "README.md").read_text()
    section = text.split("### Scenario keys", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `([\w.]+)` \| ([^|]+?) \| ([^|]+?) \|", section, flags=re.MULTILINE)
    assert rows, "no scenario-key table in the README"
    return rows


def problems(table, schema):
    """What differs between the README's rows and the schema's keys."""
    keys = [k for k, _, _ in table]
    expected = {key: (kind, required) for key, kind, required in schema}
    found = [f"{k}: listed twice" for k in sorted({k for k in keys if keys.count(k) > 1})]
    found += [f"{k}: missing from the README" for k in sorted(set(expected) - set(keys))]
    found += [f"{k}: not a scenario key" for k in sorted(set(keys) - set(expected))]
    for key, kind, required in table:
        if key not in expected:
            continue
        if kind != expected[key][0]:
            found.append(f"{key}: README says {kind}, the schema {expected[key][0]}")
        want = (
            "one of `system`, `plant`" if key in EITHER else ("yes" if expected[key][1] else "no")
        )
        if required != want:
            found.append(f"{key}: README says required={required!r}, the schema {want!r}")
    return found


def test_the_table_lists_every_key_once_with_its_type_and_whether_it_is_required():
    assert problems(readme_keys(), list(schema_keys())) == []


def test_a_drift_is_seen():
    table, schema = readme_keys(), list(schema_keys())
    assert problems(table[1:], schema) == [f"{table[0][0]}: missing from the README"]
    assert problems([*table, ("critic.kappa", "number", "no")], schema) == [
        "critic.kappa: not a scenario key"
    ]
    renamed = [(k, "integer" if k == "critic.kc" else t, r) for k, t, r in table]
    assert problems(renamed, schema) == ["critic.kc: README says integer, the schema number"]


def test_the_your_own_plant_example_builds_a_vectorized_system(tmp_path):
    """The README's module, saved beside a scenario, is what `system: my_plant:make_plant` runs."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Your own plant", 1)[1]
    module = re.search(r"```python\n(.*?)```", section, flags=re.DOTALL)[1]
    assert "# my_plant.py" in module
    assert "system: my_plant:make_plant" in section
    (tmp_path / "my_plant.py").write_text(module)
    from ofrl_drake.plants import system_from_entry

    system = system_from_entry(f"{tmp_path / 'my_plant.py'}:make_plant")
    assert (system.n, system.m, system.q) == (2, 1, 1)
    assert system.vectorized  # the 0 * x[0] convention makes f and g accept batches


def _python_blocks(text):
    return re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)


def test_the_readme_python_example_runs():
    """The first ```python block (section "Python") runs as printed, from the repository root."""
    blocks = _python_blocks((ROOT / "README.md").read_text())
    assert blocks, "the README has no ```python block"
    proc = subprocess.run(
        [sys.executable, "-c", blocks[0]],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == "2"  # the observer's estimated_state port has n = 2 entries
    assert lines[-1] == "ok ok"
