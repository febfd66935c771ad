"""The README and the pages of docs/ say what the code does.

Every relative link resolves (file and heading); every ``ofrl-drake`` command
shown parses with the real parser and names a scenario that exists; docs/cli.md
lists every option of every subcommand and every exit code; docs/scenario.md's
key table matches the scenario dataclasses; the README's Python example and
docs/own_plant.md's plant module run; the README stays an entry point that
links every page, with the test command CI runs.
"""

import argparse
import dataclasses
import re
import shlex
import subprocess
import sys
import types
import typing
from pathlib import Path

from ofrl_drake import cli
from ofrl_drake.scenario import Scenario

from .conftest import ROOT

README = ROOT / "README.md"
DOCS = ROOT / "docs"
#: Every page checked: the README and the Markdown pages of docs/.
PAGES = [README, *sorted(DOCS.glob("*.md"))]
CLI_PAGE = DOCS / "cli.md"
SCENARIO_PAGE = DOCS / "scenario.md"
OWN_PLANT_PAGE = DOCS / "own_plant.md"

#: The README is an entry point, the reference is in docs/.
README_MAX_LINES = 300


def _name(page: Path) -> str:
    return page.relative_to(ROOT).as_posix()


def _without_code(text: str) -> str:
    """``text`` without its fenced code blocks (links and headings there are not Markdown)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.DOTALL | re.MULTILINE)


def _section(text: str, heading: str) -> str:
    """The body of the section ``heading`` (a whole heading line), up to the next ``## ``."""
    assert f"\n{heading}\n" in text, f"no section {heading!r}"
    return text.split(f"\n{heading}\n", 1)[1].split("\n## ", 1)[0]


# --- links -----------------------------------------------------------------------------------


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link keeps its text
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set[str]:
    """The anchors of every heading of a Markdown text (a repeated one gets -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6} (.+)$", _without_code(text), flags=re.MULTILINE):
        base = slug(heading)
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f"{base}-{count}")
    return out


def links(text: str) -> list[str]:
    """Targets of the Markdown links and images of ``text``, outside code blocks."""
    return re.findall(r"!?\[[^\]]*\]\(([^)\s]+)\)", _without_code(text))


def link_problems(page: Path, text: str) -> list[str]:
    """Every relative link of ``text`` (the contents of ``page``) that does not resolve."""
    found = []
    for target in links(text):
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        if not file:  # a heading of this page
            if anchor not in anchors(text):
                found.append(f"{_name(page)}: {target}: no heading #{anchor} in this page")
            continue
        path = (page.parent / file).resolve()
        if ROOT not in path.parents:
            found.append(f"{_name(page)}: {target}: outside the repository")
        elif not path.exists():
            found.append(f"{_name(page)}: {target}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path.read_text()):
            found.append(f"{_name(page)}: {target}: no heading #{anchor} in {_name(path)}")
    return found


def test_every_relative_link_resolves_to_a_file_and_a_heading():
    assert [p for page in PAGES for p in link_problems(page, page.read_text())] == []


def test_a_broken_link_is_seen():
    page = DOCS / "page.md"
    text = (
        "[ok](cli.md#exit-codes) [file](missing.md) [heading](cli.md#no-such-heading) "
        "[here](#top) [there](#bottom) ![img](diagram.svg) [web](https://drake.mit.edu) "
        "[up](../../x.md)\n\n# Top\n```\n[in code](nowhere.md)\n# not a heading\n```\n"
    )
    assert link_problems(page, text) == [
        "docs/page.md: missing.md: no such file",
        "docs/page.md: cli.md#no-such-heading: no heading #no-such-heading in docs/cli.md",
        "docs/page.md: #bottom: no heading #bottom in this page",
        "docs/page.md: ../../x.md: outside the repository",
    ]


def test_anchors_follow_github():
    assert slug("`ofrl-drake run`") == "ofrl-drake-run"
    assert slug("The blocks: C++ symbolic against Python") == "the-blocks-c-symbolic-against-python"
    assert slug("What the observer certificate does, and does not, prove") == (
        "what-the-observer-certificate-does-and-does-not-prove"
    )
    assert anchors("# A\n## A\n```\n# not a heading\n```\n") == {"a", "a-1"}


def test_the_readme_links_every_docs_page_and_the_index_lists_them():
    pages = {p.name for p in DOCS.glob("*.md")} - {"README.md"}
    readme = {Path(t.partition("#")[0]).name for t in links(README.read_text())}
    index = {Path(t.partition("#")[0]).name for t in links((DOCS / "README.md").read_text())}
    assert sorted((pages | {"README.md"}) - readme) == []
    assert sorted(pages - index) == []


# --- the README as an entry point --------------------------------------------------------------


def test_the_readme_is_an_entry_point():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines, more than {README_MAX_LINES}: move reference "
        "material to a page of docs/"
    )


def test_the_readme_test_command_is_what_ci_runs():
    readme = README.read_text()
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    command = next(line for line in ci if "python -m pytest" in line)
    assert f"```bash\n{command}\n```" in readme


def test_the_citation_names_the_installed_version():
    from ofrl_drake import __version__

    versions = re.findall(r"version\s*=\s*\{([^}]*)\}", _section(README.read_text(), "## Citation"))
    assert versions == [__version__]


# --- the command line --------------------------------------------------------------------------


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def parser_options(parser: argparse.ArgumentParser) -> list[str]:
    """A subcommand's arguments as docs/cli.md names them: ``--long`` and ``POSITIONAL``."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        out.append(max(action.option_strings, key=len) if action.option_strings else action.dest)
    return [o if o.startswith("-") else o.upper() for o in out]


def cli_examples(text: str) -> list[list[str]]:
    """Arguments of every ``ofrl-drake`` command in the ```bash blocks of ``text``."""
    found = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.DOTALL):
        for line in block.splitlines():
            for part in line.split("&&"):
                words = shlex.split(part, comments=True)
                if words[:1] == ["ofrl-drake"]:
                    found.append(words[1:])
    return found


def example_problems(examples: list[list[str]]) -> list[str]:
    """Commands that the parser refuses, or whose scenario file does not exist."""
    parser = cli._parser()
    found = []
    for argv in examples:
        shown = shlex.join(["ofrl-drake", *argv])
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            found.append(f"{shown}: the parser refuses it")
            continue
        scenario = getattr(args, "scenario", None)  # plot takes a run folder, not a scenario
        if scenario is not None and not (ROOT / scenario).is_file():
            found.append(f"{shown}: no scenario file {scenario}")
    return found


def test_every_command_shown_parses_and_names_an_existing_scenario(capsys):
    examples = {_name(page): cli_examples(page.read_text()) for page in PAGES}
    assert examples["README.md"], "the README shows no ofrl-drake command"
    assert {name: example_problems(argv) for name, argv in examples.items()} == {
        name: [] for name in examples
    }
    shown = {argv[0] for argv in examples["docs/cli.md"]}
    assert sorted(set(_subparsers(cli._parser())) - shown) == []


def test_a_command_that_does_not_parse_is_seen(capsys):
    assert example_problems(
        [
            ["run", "diagrams/two_state_paper.yaml", "--out", "o"],
            ["run", "diagrams/two_state_paper.yaml", "--outt", "o"],
            ["ablate", "diagrams/nope.yaml", "--out", "o"],
        ]
    ) == [
        "ofrl-drake run diagrams/two_state_paper.yaml --outt o: the parser refuses it",
        "ofrl-drake ablate diagrams/nope.yaml --out o: no scenario file diagrams/nope.yaml",
    ]
    assert cli_examples("```bash\nx && ofrl-drake run a.yaml --out b   # then\n```\n") == [
        ["run", "a.yaml", "--out", "b"]
    ]


def option_rows(text: str, command: str) -> list[str]:
    """The first cell of each row of ``command``'s options table in docs/cli.md."""
    section = _section(text, f"## `ofrl-drake {command}`")
    table = section.split("| option | default | meaning |\n| --- | --- | --- |\n", 1)
    assert len(table) == 2, f"no options table under ofrl-drake {command}"
    rows = re.findall(r"^\| `([^`]+)` \|", table[1].split("\n\n", 1)[0], flags=re.MULTILINE)
    return [row.split()[0] for row in rows]


def option_problems(text: str, parser: argparse.ArgumentParser) -> list[str]:
    """What differs between docs/cli.md's options tables and the parser."""
    found = []
    for command, sub in _subparsers(parser).items():
        if f"\n## `ofrl-drake {command}`\n" not in text:
            found.append(f"{command}: no section in docs/cli.md")
            continue
        rows, options = option_rows(text, command), parser_options(sub)
        found += [
            f"{command} {o}: listed twice" for o in sorted({o for o in rows if rows.count(o) > 1})
        ]
        found += [f"{command} {o}: missing from docs/cli.md" for o in options if o not in rows]
        found += [f"{command} {o}: not an option" for o in rows if o not in options]
    return found


def test_the_cli_page_lists_every_option_of_every_command():
    assert option_problems(CLI_PAGE.read_text(), cli._parser()) == []


def test_a_missing_or_unknown_option_is_seen():
    text = CLI_PAGE.read_text()
    parser = cli._parser()
    assert option_problems(text.replace("| `--retry-failed` |", "| `--retry` |"), parser) == [
        "ablate --retry-failed: missing from docs/cli.md",
        "ablate --retry: not an option",
    ]
    assert option_problems(
        text.replace("## `ofrl-drake montecarlo`", "## Monte Carlo"), parser
    ) == ["montecarlo: no section in docs/cli.md"]


def test_the_exit_code_table_lists_every_exit_code():
    section = _section(CLI_PAGE.read_text(), "## Exit codes")
    listed = [int(c) for c in re.findall(r"^\| (\d+) \|", section, flags=re.MULTILINE)]
    codes = sorted(v for k, v in vars(cli).items() if k.startswith("EXIT_"))
    assert listed == codes


# --- the scenario keys -------------------------------------------------------------------------

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


def documented_keys():
    section = _section(SCENARIO_PAGE.read_text(), "## Scenario keys")
    rows = re.findall(r"^\| `([\w.]+)` \| ([^|]+?) \| ([^|]+?) \|", section, flags=re.MULTILINE)
    assert rows, "no scenario-key table in docs/scenario.md"
    return rows


def problems(table, schema):
    """What differs between docs/scenario.md's rows and the schema's keys."""
    keys = [k for k, _, _ in table]
    expected = {key: (kind, required) for key, kind, required in schema}
    found = [f"{k}: listed twice" for k in sorted({k for k in keys if keys.count(k) > 1})]
    found += [f"{k}: missing from docs/scenario.md" for k in sorted(set(expected) - set(keys))]
    found += [f"{k}: not a scenario key" for k in sorted(set(keys) - set(expected))]
    for key, kind, required in table:
        if key not in expected:
            continue
        if kind != expected[key][0]:
            found.append(f"{key}: docs/scenario.md says {kind}, the schema {expected[key][0]}")
        want = (
            "one of `system`, `plant`" if key in EITHER else ("yes" if expected[key][1] else "no")
        )
        if required != want:
            found.append(f"{key}: docs/scenario.md says required={required!r}, the schema {want!r}")
    return found


def test_the_table_lists_every_key_once_with_its_type_and_whether_it_is_required():
    assert problems(documented_keys(), list(schema_keys())) == []


def test_a_drift_is_seen():
    table, schema = documented_keys(), list(schema_keys())
    assert problems(table[1:], schema) == [f"{table[0][0]}: missing from docs/scenario.md"]
    assert problems([*table, ("critic.kappa", "number", "no")], schema) == [
        "critic.kappa: not a scenario key"
    ]
    renamed = [(k, "integer" if k == "critic.kc" else t, r) for k, t, r in table]
    assert problems(renamed, schema) == [
        "critic.kc: docs/scenario.md says integer, the schema number"
    ]


# --- the code shown runs -----------------------------------------------------------------------


def _python_blocks(text):
    return re.findall(r"```python\n(.*?)```", text, flags=re.DOTALL)


def test_the_your_own_plant_example_builds_a_vectorized_system(tmp_path):
    """docs/own_plant.md's module, saved beside a scenario, is what `system: my_plant:make_plant`
    runs."""
    text = OWN_PLANT_PAGE.read_text()
    section = _section(text, "## A Python function")
    module = _python_blocks(section)[0]
    assert "# my_plant.py" in module
    assert "system: my_plant:make_plant" in section
    (tmp_path / "my_plant.py").write_text(module)
    from ofrl_drake.plants import system_from_entry

    system = system_from_entry(f"{tmp_path / 'my_plant.py'}:make_plant")
    assert (system.n, system.m, system.q) == (2, 1, 1)
    assert system.vectorized  # the 0 * x[0] convention makes f and g accept batches


def test_the_readme_python_example_runs():
    """The README's ```python block (section "Python") runs as printed, from the repository root."""
    blocks = _python_blocks(_section(README.read_text(), "## Python"))
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
