"""Every code symbol, constant and config key the docs name exists, with the value they state.

The convention docs/*.md and README.md follow (and this test resolves, by reading the code with
`ast`, so nothing is imported but the config dataclasses):
- a file in a code span: `kit/bus/session.py` (a path from the repository root; a bare `session.py`
  must name a file somewhere in the packages, bench/ or tests/);
- a symbol: `mapper/core.py: Mapper.integrate` (file, colon, a name defined at its top level, then
  attributes: a class's methods, class attributes, dataclass fields or `self.` attributes), or the
  installed dotted name `octolog.kit.tum.TUM_READOUT_S`;
- a config key: `tracker.live_lag_ms`, also as `--set` takes it (`tracker.live=true`), for the
  sections `recorder`, `replay`, `tracker`, `mapper`;
- a value: a symbol or key followed by its value in parentheses, `schemas/checks.py: MAX_SIDE` (8192),
  `tracker.live_lag_ms` (100 ms); the number must equal the constant's literal value or the key's
  default. (A `key=value` inside the span is a setting, not a claim about the default.)
Names without a file (`Mapper.rebuild`) are prose and are not resolved.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import operator
import re
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
PACKAGES = ("kit", "schemas", "recorder", "replay", "tracker", "mapper", "shell")
CONFIGS = {
    "recorder": "octolog.recorder.config:RecorderConfig",
    "replay": "octolog.replay.config:ReplayConfig",
    "tracker": "octolog.tracker.config:TrackerConfig",
    "mapper": "octolog.mapper.config:MapperConfig",
}
_SPAN = re.compile(r"`([^`\n]+)`(?:\s*\((-?\d[\d,]*(?:\.\d+)?))?")
_FILE_SYMBOL = re.compile(r"^((?:[\w.]+/)*\w+\.py)(?::\s*([A-Za-z_][\w.]*))?$")
_DOTTED = re.compile(r"^octolog(?:\.[A-Za-z_]\w*)+$")
_KEY = re.compile(rf"^({'|'.join(CONFIGS)})\.([a-z_][\w.]*?)\s*(=.*)?$")
MISSING = object()


# --- reading the code ---------------------------------------------------------------------------


def module_file(dotted: str, root: Path = ROOT) -> Path | None:
    """`octolog.kit.tum` -> kit/tum.py (or a package's __init__.py); None when there is none."""
    parts = dotted.split(".")[1:]
    base = root / "octolog" if not parts or parts[0] not in PACKAGES else root
    for candidate in (base.joinpath(*parts).with_suffix(".py") if parts else None,
                      base.joinpath(*parts, "__init__.py")):
        if candidate is not None and candidate.is_file():
            return candidate
    return None


def _top_level(body: list[ast.stmt]) -> list[ast.stmt]:
    """Statements of a body, with those inside if/try blocks flattened in."""
    out: list[ast.stmt] = []
    for node in body:
        out.append(node)
        if isinstance(node, ast.If):
            out += _top_level(node.body) + _top_level(node.orelse)
        elif isinstance(node, ast.Try):
            out += _top_level(node.body) + _top_level(node.orelse) + _top_level(node.finalbody)
            for handler in node.handlers:
                out += _top_level(handler.body)
    return out


_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
        ast.FloorDiv: operator.floordiv, ast.Pow: operator.pow}


def literal(node: ast.AST | None) -> Any:
    """The value of a literal expression (arithmetic on numbers included), else MISSING."""
    if node is None:
        return MISSING
    if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
        left, right = literal(node.left), literal(node.right)
        if isinstance(left, (int, float)) and isinstance(right, (int, float)):
            return _OPS[type(node.op)](left, right)
        return MISSING
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "field":
        for kw in node.keywords:
            if kw.arg == "default":
                return literal(kw.value)
        return MISSING
    try:
        return ast.literal_eval(node)
    except ValueError:
        return MISSING


def _assigned(node: ast.stmt) -> dict[str, ast.AST | None]:
    if isinstance(node, ast.Assign):
        return {t.id: node.value for t in node.targets if isinstance(t, ast.Name)}
    if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
        return {node.target.id: node.value}
    return {}


def _self_attributes(cls: ast.ClassDef) -> set[str]:
    return {t.attr for n in ast.walk(cls) if isinstance(n, (ast.Assign, ast.AnnAssign))
            for t in (n.targets if isinstance(n, ast.Assign) else [n.target])
            if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self"}


def _imported_from(node: ast.ImportFrom, path: Path, root: Path) -> str | None:
    """The dotted first-party module an import reads from, or None for a third-party one."""
    if node.level:
        package = path.parent
        for _ in range(node.level - 1):
            package = package.parent
        rel = package.relative_to(root).parts
        base = "octolog" + "".join(f".{p}" for p in rel if p != "octolog")
        return base + (f".{node.module}" if node.module else "")
    if node.module and (node.module == "octolog" or node.module.startswith("octolog.")):
        return node.module
    return None


def resolve(path: Path, names: list[str], root: Path = ROOT, depth: int = 0) -> tuple[str, Any]:
    """("" when found, else why not; the literal value when the last name is a plain assignment)."""
    tree = ast.parse(path.read_text(), str(path))
    body, here = _top_level(tree.body), path.relative_to(root)
    first, rest = names[0], names[1:]
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == first:
            if not rest:
                return "", MISSING
            if not isinstance(node, ast.ClassDef):
                return f"{here}: {first} is a function, it has no {'.'.join(rest)}", MISSING
            return _resolve_in_class(node, rest, here)
        values = _assigned(node)
        if first in values:
            return ("", literal(values[first])) if not rest else ("", MISSING)
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if (alias.asname or alias.name) == first:
                    source = _imported_from(node, path, root)
                    if source is None or depth > 4:
                        return "", MISSING
                    target = module_file(f"{source}.{alias.name}", root)
                    if target is not None:  # a submodule
                        return resolve(target, rest, root, depth + 1) if rest else ("", MISSING)
                    target = module_file(source, root)
                    if target is None:
                        return f"{here}: imports {first} from {source}, which has no file", MISSING
                    return resolve(target, [alias.name, *rest], root, depth + 1)
    return f"{here} defines no {first}", MISSING


def _resolve_in_class(cls: ast.ClassDef, names: list[str], here: Path) -> tuple[str, Any]:
    name = names[0]
    for node in _top_level(cls.body):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == name:
            if len(names) > 1 and isinstance(node, ast.ClassDef):
                return _resolve_in_class(node, names[1:], here)
            return "", MISSING
        values = _assigned(node)
        if name in values:
            return "", literal(values[name]) if len(names) == 1 else MISSING
    if name in _self_attributes(cls):
        return "", MISSING
    return f"{here}: class {cls.name} has no {name}", MISSING


def bare_files(root: Path = ROOT) -> set[str]:
    out = set()
    for folder in (*PACKAGES, "octolog", "bench", "tests"):
        out |= {p.name for p in (root / folder).rglob("*.py")}
    return out


def config_defaults() -> dict[str, dict[str, Any]]:
    """Section -> dotted key -> resolved default (nested tables flattened)."""
    from octolog.kit.config import from_dict

    out: dict[str, dict[str, Any]] = {}
    for section, spec in CONFIGS.items():
        module, _, name = spec.partition(":")
        flat: dict[str, Any] = {}

        def walk(obj: Any, prefix: str) -> None:
            for field in dataclasses.fields(obj):
                value = getattr(obj, field.name)
                flat[prefix + field.name] = value
                if dataclasses.is_dataclass(value):
                    walk(value, f"{prefix}{field.name}.")

        walk(from_dict(getattr(importlib.import_module(module), name), {}), "")
        out[section] = flat
    return out


# --- checking the docs --------------------------------------------------------------------------


def _number(text: str) -> float:
    return float(text.replace(",", ""))


def _value_problem(where: str, span: str, stated: str | None, value: Any) -> str | None:
    if stated is None or value is MISSING or isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if _number(stated) != float(value):
        return f"{where}: `{span}` ({stated}): the code says {value!r}"
    return None


def mention_problems(text: str, where: str, root: Path = ROOT,
                     defaults: dict[str, dict[str, Any]] | None = None) -> list[str]:
    """Every mention in `text` that does not resolve, or states a value the code does not have."""
    problems: list[str] = []
    files = bare_files(root)
    for lineno, line in enumerate(text.splitlines(), 1):
        at = f"{where}:{lineno}"
        for m in _SPAN.finditer(line):
            span, stated = m[1].strip(), m[2]
            if (fm := _FILE_SYMBOL.match(span)) is not None:
                rel, symbol = fm[1], fm[2]
                if "/" not in rel:
                    if rel not in files:
                        problems.append(f"{at}: `{span}`: no file {rel} in the repository")
                    continue
                path = root / rel
                if not path.is_file():
                    problems.append(f"{at}: `{span}`: {rel} does not exist")
                    continue
                if symbol:
                    why, value = resolve(path, symbol.split("."), root)
                    problems += [f"{at}: `{span}`: {why}"] if why else []
                    if not why and (p := _value_problem(at, span, stated, value)):
                        problems.append(p)
            elif _DOTTED.match(span):
                parts = span.split(".")
                for cut in range(len(parts), 0, -1):
                    path = module_file(".".join(parts[:cut]), root)
                    if path is not None:
                        break
                if path is None:
                    problems.append(f"{at}: `{span}`: no module of that name")
                    continue
                if parts[cut:]:
                    why, value = resolve(path, parts[cut:], root)
                    problems += [f"{at}: `{span}`: {why}"] if why else []
                    if not why and (p := _value_problem(at, span, stated, value)):
                        problems.append(p)
            elif (km := _KEY.match(span)) is not None:
                defaults = config_defaults() if defaults is None else defaults
                section, key, setting = km[1], km[2], km[3]
                if key not in defaults[section]:
                    problems.append(f"{at}: `{span}`: [{section}] has no key {key}")
                elif setting is None and (p := _value_problem(at, span, stated, defaults[section][key])):
                    problems.append(p)
    return problems


def test_every_symbol_the_docs_name_exists_with_its_value():
    defaults = config_defaults()
    problems = []
    for doc in DOCS:
        problems += mention_problems(doc.read_text(), str(doc.relative_to(ROOT)), ROOT, defaults)
    if problems:
        pytest.fail("the docs name code that is not there (fix the mention, or the code if the docs "
                    "were right):\n" + "\n".join(problems), pytrace=False)


def test_the_check_fails_on_wrong_mentions():
    """Made-up mentions, each wrong in one way, are all reported; their right forms are not."""
    right = ("`schemas/checks.py: MAX_SIDE` (8192) `kit/bus/session.py` `session.py` "
             "`octolog.kit.tum.TUM_READOUT_S` `tracker.live_lag_ms` (100 ms) `tracker.live=true` "
             "`mapper/core.py: Mapper.integrate` `octolog.kit.bus.Bus`")
    assert mention_problems(right, "right") == []
    wrong = {
        "`schemas/checks.py: MAX_SIDE` (16384)": "the code says 8192",
        "`kit/tum.py: NO_SUCH_READER`": "defines no NO_SUCH_READER",
        "`mapper/core.py: Mapper.no_such_method`": "has no no_such_method",
        "`kit/no_such_module.py`": "does not exist",
        "`no_such_module.py`": "no file no_such_module.py",
        "`octolog.kit.tum.NO_SUCH`": "defines no NO_SUCH",
        "`octolog.kit.no_such`": "defines no no_such",
        "`tracker.no_such_key`": "has no key no_such_key",
        "`tracker.live_lag_ms` (15 ms)": "the code says 100",
    }
    for mention, expected in wrong.items():
        problems = mention_problems(mention, "made-up")
        assert len(problems) == 1 and expected in problems[0], f"{mention}: {problems}"
