"""docs/cli.md cannot drift from the code: config keys and defaults, subcommands and flags.

The format docs/cli.md keeps (and this test parses):
- `## Commands`: a table whose rows start with a code span `octolog COMMAND ...`; a command may have
  several rows (`octolog replay --source ...`, `octolog replay SESSION ...`). Every flag of a command
  appears in one of its rows or in `## Shared options`; every flag a row names exists on that command.
- `## Config keys`: one `### SECTION` per section of the TOML config (`[recorder]`, `[replay]`,
  `[tracker]`, `[mapper]`), each a table `| key | default | meaning |`. Keys of nested tables are
  dotted (`color.width`). A default is a TOML value in a code span, as `--set KEY=VALUE` takes it
  (`0.05`, `true`, `"jpeg"`, `["tracker"]`), or the bare word `unset` for a key without one (None).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
CLI_MD = ROOT / "docs" / "cli.md"
# TOML section -> the stage config dataclass it loads into (shell/cli.py, shell/record.py, shell/run.py)
SECTIONS = {
    "recorder": "octolog.recorder.config:RecorderConfig",
    "replay": "octolog.replay.config:ReplayConfig",
    "tracker": "octolog.tracker.config:TrackerConfig",
    "mapper": "octolog.mapper.config:MapperConfig",
}
UNSET = "unset"
_ROW = re.compile(r"^\|(.*)\|\s*$")


def sections(text: str, level: str) -> dict[str, list[str]]:
    """Heading text -> its lines, for headings of exactly `level` (e.g. "##")."""
    out: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in text.splitlines():
        m = re.match(r"^(#+)\s+(.*?)\s*$", line)
        if m and len(m[1]) <= len(level):
            current = out.setdefault(m[2], []) if m[1] == level else None
        elif current is not None:
            current.append(line)
    return out


def table_rows(lines: list[str]) -> list[tuple[int, list[str]]]:
    """(index in lines, cells) of a markdown table's body rows (header and separator left out)."""
    rows, previous = [], ""
    for i, line in enumerate(lines):
        m = _ROW.match(line.strip())
        if m and not re.fullmatch(r"[\s|:-]+", m[1]) and _ROW.match(previous) is None:
            previous = line.strip()  # the header row
            continue
        if m and not re.fullmatch(r"[\s|:-]+", m[1]):
            rows.append((i, [c.strip() for c in re.split(r"(?<!\\)\|", m[1])]))
        previous = line.strip() if m else ""
    return rows


def doc() -> str:
    return CLI_MD.read_text()


# --- config keys --------------------------------------------------------------------------------


def resolved_defaults(cls: type) -> dict[str, Any]:
    """Dotted key -> default, as the loader resolves an empty config (nested tables flattened)."""
    from octolog.kit.config import from_dict

    out: dict[str, Any] = {}

    def walk(obj: Any, prefix: str) -> None:
        for field in dataclasses.fields(obj):
            value = getattr(obj, field.name)
            if dataclasses.is_dataclass(value):
                walk(value, f"{prefix}{field.name}.")
            else:
                out[prefix + field.name] = value

    walk(from_dict(cls, {}), "")
    return out


def documented_keys(section: str) -> dict[str, tuple[str, str]]:
    """Dotted key -> (default cell, meaning) from `### section` under `## Config keys`."""
    config = sections(doc(), "##").get("Config keys")
    assert config is not None, "docs/cli.md: no `## Config keys` section"
    lines = sections("\n".join(config), "###").get(section)
    assert lines is not None, f"docs/cli.md: no `### {section}` table under `## Config keys`: add one"
    out: dict[str, tuple[str, str]] = {}
    for _, cells in table_rows(lines):
        assert len(cells) == 3, f"docs/cli.md [{section}]: want | key | default | meaning |, got {cells}"
        key, default, meaning = cells
        m = re.fullmatch(r"`([\w.]+)`", key)
        assert m, f"docs/cli.md [{section}]: key cell {key!r}: want the key in a code span, e.g. `rate`"
        assert m[1] not in out, f"docs/cli.md [{section}]: key {m[1]!r} listed twice"
        out[m[1]] = (default, meaning)
    return out


def parse_default(cell: str) -> Any:
    if cell == UNSET:
        return None
    m = re.fullmatch(r"`(.+)`", cell)
    if not m:
        raise ValueError(f"want a TOML value in a code span or the word {UNSET}")
    try:
        return tomllib.loads(f"v = {m[1]}")["v"]
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"not a TOML value ({exc})") from None


def same(doc_value: Any, value: Any) -> bool:
    """TOML value == Python default, strictly on kinds (true is not 1, "1" is not 1; 0 is 0.0)."""
    if isinstance(value, bool) or isinstance(doc_value, bool):
        return type(doc_value) is type(value) and doc_value == value
    if isinstance(value, (int, float)):
        return isinstance(doc_value, (int, float)) and float(doc_value) == float(value)
    if isinstance(value, (list, tuple)):
        return (isinstance(doc_value, list) and len(doc_value) == len(value)
                and all(same(d, v) for d, v in zip(doc_value, value)))
    return type(doc_value) is type(value) and doc_value == value


def toml_text(value: Any) -> str:
    if value is None:
        return UNSET
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    if isinstance(value, str):
        return f"`{json.dumps(value)}`"
    if isinstance(value, (list, tuple)):
        return "`[" + ", ".join(toml_text(v).strip("`") for v in value) + "]`"
    return f"`{value!r}`"


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_config_keys_and_defaults_are_documented(section):
    module, _, name = SECTIONS[section].partition(":")
    defaults = resolved_defaults(getattr(importlib.import_module(module), name))
    documented = documented_keys(section)
    problems = []
    for key, value in defaults.items():
        if key not in documented:
            problems.append(f"[{section}] {key} (default {toml_text(value)}) is missing: add a row "
                            f"| `{key}` | {toml_text(value)} | what it does |")
            continue
        cell, meaning = documented[key]
        try:
            doc_value = parse_default(cell)
        except ValueError as exc:
            problems.append(f"[{section}] {key}: default cell {cell!r}: {exc}")
            continue
        if not same(doc_value, value):
            problems.append(f"[{section}] {key}: docs say {cell}, the resolved default is {toml_text(value)}: "
                            f"fix the row (or the code, if the docs were right)")
        if not meaning.strip():
            problems.append(f"[{section}] {key}: the meaning cell is empty: say what it does")
    for key in documented.keys() - defaults.keys():
        problems.append(f"[{section}] {key} is documented but {name} has no such key: remove or rename the row")
    if problems:
        pytest.fail(f"docs/cli.md `## Config keys` drifted from {name}:\n" + "\n".join(problems), pytrace=False)


def test_parse_and_compare_defaults():
    """The cell parser and comparison themselves: kinds count, tuples are lists, `unset` is None."""
    assert parse_default("`0.05`") == 0.05 and parse_default(UNSET) is None
    assert same(parse_default('`["tracker"]`'), ("tracker",)) and same(parse_default("`[[0.0, 1]]`"), ((0.0, 1.0),))
    assert not same(parse_default("`1`"), True) and not same(parse_default('`"1"`'), 1)
    assert not same(parse_default("`2.0`"), 3.0) and same(parse_default("`0`"), 0.0)
    with pytest.raises(ValueError):
        parse_default("2.0")
    for value in (0.05, True, "jpeg", ("a", "b"), (), ((0.0, -1.0),), None, 60):
        assert same(parse_default(toml_text(value)), value)


# --- commands and flags -------------------------------------------------------------------------


def commands() -> dict[str, argparse.ArgumentParser]:
    """Command path ("run", "vocab build") -> its parser, walking build_parser()'s subparsers."""
    from octolog.shell.cli import build_parser

    out: dict[str, argparse.ArgumentParser] = {}

    def walk(parser: argparse.ArgumentParser, path: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    out[f"{path} {name}".strip()] = sub
                    walk(sub, f"{path} {name}")

    walk(build_parser(), "")
    assert out, "build_parser() has no subcommands"
    return out


def long_flags(parser: argparse.ArgumentParser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings if o.startswith("--") and o != "--help"}


def _flags_in(text: str) -> set[str]:
    return set(re.findall(r"(?<![\w-])(--[a-z][\w-]*)", text))


def command_rows() -> list[tuple[str, str]]:
    """(`octolog ...` code span of the first cell, whole row) of the `## Commands` table."""
    lines = sections(doc(), "##").get("Commands")
    assert lines is not None, "docs/cli.md: no `## Commands` section"
    out = []
    for i, cells in table_rows(lines):
        m = re.match(r"`(octolog[^`]*)`", cells[0])
        assert m, f"docs/cli.md `## Commands`: row {cells[0]!r}: want a first cell starting `octolog COMMAND`"
        out.append((m[1], lines[i]))
    return out


def rows_of(path: str, rows: list[tuple[str, str]]) -> list[str]:
    return [row for code, row in rows if code == f"octolog {path}" or code.startswith(f"octolog {path} ")]


def test_every_command_and_flag_is_documented():
    rows = command_rows()
    shared_lines = sections(doc(), "##").get("Shared options")
    assert shared_lines is not None, "docs/cli.md: no `## Shared options` section"
    shared = _flags_in("\n".join(shared_lines))
    problems = []
    for path, parser in commands().items():
        mine = rows_of(path, rows)
        if not mine:
            problems.append(f"`octolog {path}` has no row in `## Commands`: "
                            f"add | `octolog {path} ...` | what it does |")
            continue
        in_rows = _flags_in("\n".join(mine))
        flags = long_flags(parser)
        for flag in sorted(flags - in_rows - shared):
            problems.append(f"`octolog {path} {flag}` is not documented: name it in the command's row "
                            f"(or in `## Shared options` if several commands share it)")
        nested = {f for p, sub in commands().items() if p.startswith(f"{path} ") for f in long_flags(sub)}
        for flag in sorted(in_rows - flags - nested):
            problems.append(f"`octolog {path}` row names {flag}, which `octolog {path}` does not have")
    everything = {f for parser in commands().values() for f in long_flags(parser)}
    for flag in sorted(shared - everything):
        problems.append(f"`## Shared options` names {flag}, which no command has")
    if problems:
        pytest.fail("docs/cli.md drifted from build_parser():\n" + "\n".join(problems), pytrace=False)
