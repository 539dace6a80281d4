"""The README's tool tables are checked against the tools' argument parsers, not copied from them: every
option of every console script of setup.py is listed with its default, every option the README names
exists, and every ``--help`` states the defaults."""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()

#: Console scripts without an argparse parser, with the reason: ROS nodes, configured by ROS arguments
#: (``--ros-args``) and parameters, which the README's node-suite section lists.
ROS_NODES = {"landmark_detector", "topology_filter", "map_publisher"}


def console_scripts() -> dict[str, str]:
    """setup.py's console scripts: name -> module (``ptm-run`` -> ``ptm_ros.tools.run``)."""
    tree = ast.parse((REPO / "setup.py").read_text())
    lists = [
        node.values[node.keys.index(key)]
        for node in ast.walk(tree)
        if isinstance(node, ast.Dict)
        for key in node.keys
        if isinstance(key, ast.Constant) and key.value == "console_scripts"
    ]
    (entries,) = lists
    pairs = (ast.literal_eval(e).split("=") for e in entries.elts)
    return {name.strip(): target.strip().split(":")[0] for name, target in pairs}


def has_build_parser(module: str) -> bool:
    """Whether ``module`` defines ``build_parser()`` (read from its source: no import, no rclpy)."""
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin is not None, module
    tree = ast.parse(Path(spec.origin).read_text())
    return any(isinstance(n, ast.FunctionDef) and n.name == "build_parser" for n in tree.body)


SCRIPTS = console_scripts()
TOOLS = sorted(name for name in SCRIPTS if name not in ROS_NODES)


def parser_of(tool: str) -> argparse.ArgumentParser:
    return importlib.import_module(SCRIPTS[tool]).build_parser()


def options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """The parser's long options (``--help`` aside) and their actions."""
    return {
        s: a
        for a in parser._actions
        for s in a.option_strings
        if s.startswith("--") and not isinstance(a, argparse._HelpAction)
    }


def cells(row: str) -> list[str]:
    """The cells of a Markdown table row (``\\|`` inside a cell is no separator)."""
    return [c.strip() for c in re.split(r"(?<!\\)\|", row.strip())[1:-1]]


def option_tables() -> dict[str, list[list[str]]]:
    """The rows of the README's option table of each tool (a ``#### `tool``` heading, then a table)."""
    tables: dict[str, list[list[str]]] = {}
    tool = None
    for line in README.splitlines():
        heading = re.fullmatch(r"#### `([\w-]+)`", line)
        if line.startswith("#"):
            tool = heading.group(1) if heading else None
            if tool:
                tables[tool] = []
        elif tool and line.startswith("|"):
            row = cells(line)
            if row[0] != "option" and not row[0].startswith("---"):
                tables[tool].append(row)
    return tables


TABLES = option_tables()
OPTION = re.compile(r"--[a-z][a-z0-9-]*")
NUMBER = re.compile(r"-?\d+(?:\.\d+)?")


def test_every_console_script_has_a_parser_or_is_a_ros_node():
    assert set(SCRIPTS) >= ROS_NODES
    without = {name for name, module in SCRIPTS.items() if not has_build_parser(module)}
    assert without == ROS_NODES, "a tool needs build_parser() (or is a ROS node: add it to ROS_NODES)"
    assert sorted(TABLES) == TOOLS, "one README option table per tool"


@pytest.mark.parametrize("tool", TOOLS)
def test_the_readme_table_lists_exactly_the_parsers_options(tool):
    rows = TABLES[tool]
    named = [OPTION.findall(row[0]) for row in rows]
    assert all(len(n) == 1 for n in named), f"one option per line: {[r[0] for r in rows]}"
    listed = [n[0] for n in named]
    assert len(set(listed)) == len(listed), f"listed twice: {listed}"
    actual = options(parser_of(tool))
    assert sorted(set(actual) - set(listed)) == [], f"{tool}: options missing from the README"
    assert sorted(set(listed) - set(actual)) == [], f"{tool}: README options the parser lacks"
    assert all(len(row) == 3 and all(row) for row in rows), f"{tool}: option | default | meaning"


def default_shown(default: object, cell: str) -> bool:
    """Whether a README default cell shows the parser's default (numbers compared as numbers)."""
    values = default if isinstance(default, (list, tuple)) else [default]
    numbers = {float(x) for x in NUMBER.findall(cell)}
    return all(
        float(v) in numbers if isinstance(v, (int, float)) else f"`{v}`" in cell or str(v) in cell
        for v in values
    )


@pytest.mark.parametrize("tool", TOOLS)
def test_the_readme_states_the_parsers_defaults_and_choices(tool):
    actual = options(parser_of(tool))
    for option, default, _ in TABLES[tool]:
        action = actual[OPTION.findall(option)[0]]
        if action.default is not None and action.nargs != 0:
            assert default_shown(action.default, default), (tool, option, action.default, default)
        choices = re.findall(r"`--[\w-]+ ([\w-]+(?:\\\|[\w-]+)+)`", option)
        if choices:
            assert choices[0].split("\\|") == list(action.choices), (tool, option)


@pytest.mark.parametrize("tool", TOOLS)
def test_help_states_every_default_in_user_words(tool):
    """``--help`` says what every option defaults to (``%(default)s`` where it is a value, words where
    None means "from elsewhere"); flags are off by default. No help text sends the user to Python code."""
    parser = parser_of(tool)
    for option, action in options(parser).items():
        text = action.help or ""
        if action.nargs != 0 and not action.required:
            assert "default" in text, (tool, option, text)
            if action.default is not None:
                assert "%(default)s" in text, (tool, option, text)
        assert not re.search(r"\bmodule\b|ptm_ros\.|\bio\.\w", text), (tool, option, text)
    for action in parser._actions:
        if not action.option_strings:  # positionals
            assert not re.search(r"\bmodule\b|ptm_ros\.|\bio\.\w", action.help or ""), (tool, action.dest)
    assert "%(default)" not in parser.format_help()


def command_lines() -> list[tuple[str, str]]:
    """Every README command of a tool: inline code spans and code-block lines (continuations joined)
    that run one, as (tool, the arguments after its name)."""
    blocks = re.findall(r"```[a-z]*\n(.*?)```", README, flags=re.S)
    lines = [ln for b in blocks for ln in b.replace("\\\n", " ").splitlines()]
    spans = re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", README, flags=re.S))
    found = []
    for text in lines + spans:
        for match in re.finditer(r"(?:^|[\s/])(ptm-[a-z-]+)((?:\s+[^\s#]+)*)", text):
            if match.group(1) in SCRIPTS:
                found.append((match.group(1), match.group(2)))
    return found


def test_every_readme_command_uses_options_its_tool_has():
    commands = command_lines()
    assert {tool for tool, _ in commands} == set(TOOLS)  # each tool appears at least once
    wrong = [
        (tool, opt)
        for tool, args in commands
        for opt in OPTION.findall(args)
        if opt not in options(parser_of(tool)) and opt != "--help"
    ]
    assert wrong == []


def test_the_tools_table_names_only_existing_options():
    """The summary table (tool | usage | result): every option in a tool's row is one of its own."""
    rows = [cells(ln) for ln in README.splitlines() if re.match(r"\| `ptm-[a-z-]+` \|", ln)]
    assert sorted(row[0].strip("`") for row in rows) == TOOLS
    for row in rows:
        tool = row[0].strip("`")
        unknown = set(OPTION.findall(" ".join(row[1:]))) - set(options(parser_of(tool)))
        assert unknown == set(), (tool, unknown)
