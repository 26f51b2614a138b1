"""The architecture, checked from the source: one `octolog` namespace, three floors, the kit's
layers one way, no import circles, first-party imports at module top, each transport, log and viewer
library in one module, and a stated reason for every long module and function.

Every .py file is read with `ast` (never imported): all imports count, at module level, inside
functions and under `if TYPE_CHECKING:`, plus `importlib.import_module("...")`/`__import__("...")`
with a constant name and `[sys.executable, "-m", "..."]` module names. Files map to module names
through `[tool.setuptools.package-dir]` in pyproject.toml, so the checks follow the real packaging.

Floors (docs/architecture.md):
- kit: the root `octolog` package, `octolog.kit`, `octolog.schemas`; imports no stage and not the shell;
- stages: `octolog.recorder`, `octolog.replay`, `octolog.tracker`, `octolog.mapper`; each imports
  only the kit and its own package;
- shell: `octolog.shell` (and `octolog.__main__`, the `python -m octolog` entry point); imports anything.
Inside the kit floor: the kit's basics (KIT_BELOW_SCHEMAS) <- octolog.schemas <- the rest of octolog.kit.
"""

from __future__ import annotations

import ast
import os
import tomllib
from collections import deque
from dataclasses import dataclass
from functools import cache
from itertools import pairwise
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
_SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
PACKAGE_DIR: dict[str, str] = _SETUPTOOLS["package-dir"]
PACKAGES: list[str] = _SETUPTOOLS["packages"]

KIT = ("octolog", "octolog.kit", "octolog.schemas")
STAGES = ("octolog.recorder", "octolog.replay", "octolog.tracker", "octolog.mapper")
SHELL = ("octolog.shell",)
# `python -m octolog` runs the shell; it sits on the shell floor and nothing may import it.
ENTRY_POINTS = ("octolog.__main__",)

# Folders that held top-level packages before the one namespace (`import tracker`): never again.
OLD_TOP_LEVEL = sorted({Path(folder).parts[0] for folder in PACKAGE_DIR.values()} - {"octolog"})
_SKIP_DIRS = {".git", ".venv", "venv", "build", "dist", "out", "__pycache__", "node_modules"}


@dataclass(frozen=True)
class Source:
    path: Path  # absolute
    module: str | None  # dotted name when the file is part of the installed package
    is_package: bool  # an __init__.py

    @property
    def rel(self) -> str:
        return self.path.relative_to(ROOT).as_posix()


@dataclass(frozen=True)
class Ref:
    """One reference from a file to a module: an import, a dynamic import or a `-m` module name."""

    source: Source
    line: int
    target: str  # absolute dotted name (relative imports resolved)
    name: str | None  # `from target import name`: the imported name
    kind: str  # "import", "dynamic" or "-m"

    @property
    def where(self) -> str:
        return f"{self.source.rel}:{self.line}"


def module_name(path: Path) -> tuple[str | None, bool]:
    """The installed module name of `path` per the package-dir table (longest folder wins)."""
    best: tuple[int, str, Path] | None = None
    for package, folder in PACKAGE_DIR.items():
        base = (ROOT / folder).resolve()
        if path.is_relative_to(base) and (best is None or len(base.parts) > best[0]):
            best = (len(base.parts), package, base)
    if best is None:
        return None, False
    _, package, base = best
    parts = list(path.relative_to(base).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts.pop()
    return ".".join([package, *parts]), is_package


@cache
def all_sources() -> tuple[Source, ...]:
    """Every .py file of the checkout (package code, tests, bench, docs examples, ...)."""
    out = []
    for dirpath, dirnames, filenames in os.walk(ROOT):
        dirnames[:] = sorted(d for d in dirnames
                             if d not in _SKIP_DIRS and not d.startswith(".") and not d.endswith(".egg-info"))
        for name in sorted(filenames):
            if name.endswith(".py"):
                path = Path(dirpath) / name
                out.append(Source(path, *module_name(path)))
    return tuple(out)


@cache
def package_sources() -> dict[str, Source]:
    return {s.module: s for s in all_sources() if s.module is not None}


@cache
def parse(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), filename=str(path))


def _resolve_relative(src: Source, level: int, module: str | None, line: int) -> str:
    if src.module is None:
        raise AssertionError(f"{src.rel}:{line}: relative import outside the octolog package: "
                             f"use an absolute import")
    package = src.module if src.is_package else src.module.rpartition(".")[0]
    parts = package.split(".")
    if level - 1 >= len(parts):
        raise AssertionError(f"{src.rel}:{line}: relative import goes above the top-level package")
    base = ".".join(parts[: len(parts) - (level - 1)])
    return f"{base}.{module}" if module else base


def _const_str(node: ast.AST) -> str | None:
    return node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else None


@cache
def refs_of(src: Source) -> tuple[Ref, ...]:
    out: list[Ref] = []
    for node in ast.walk(parse(src.path)):
        if isinstance(node, ast.Import):
            out += [Ref(src, node.lineno, alias.name, None, "import") for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = (_resolve_relative(src, node.level, node.module, node.lineno) if node.level
                    else node.module or "")
            out += [Ref(src, node.lineno, base, alias.name, "import") for alias in node.names]
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            fname = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
            target = _const_str(node.args[0])
            if fname in ("import_module", "__import__") and target and not target.startswith("."):
                out.append(Ref(src, node.lineno, target, None, "dynamic"))
        elif isinstance(node, (ast.List, ast.Tuple)):
            for flag, arg in pairwise(node.elts):
                target = _const_str(arg)
                if _const_str(flag) == "-m" and target:
                    out.append(Ref(src, arg.lineno, target, None, "-m"))
    return tuple(out)


def imported_module(ref: Ref) -> str | None:
    """The package module `ref` loads (`from octolog.kit import bus` -> octolog.kit.bus), if any."""
    modules = package_sources()
    if ref.name and ref.name != "*" and f"{ref.target}.{ref.name}" in modules:
        return f"{ref.target}.{ref.name}"
    parts = ref.target.split(".")
    for n in range(len(parts), 0, -1):  # `import octolog.kit.bus` also names octolog and octolog.kit
        if ".".join(parts[:n]) in modules:
            return ".".join(parts[:n])
    return None


def floor_unit(module: str) -> str:
    """The unit a module belongs to: octolog.__main__, a stage, octolog.shell or a kit package."""
    if module in ENTRY_POINTS:
        return module
    units = [u for u in (*KIT, *STAGES, *SHELL) if module == u or module.startswith(u + ".")]
    return max(units, key=len) if units else module


def floor(unit: str) -> str:
    if unit in ENTRY_POINTS or unit in SHELL:
        return "shell"
    return "stage" if unit in STAGES else "kit" if unit in KIT else "unknown"


def _fail(problems: list[str], what: str) -> None:
    problems = list(dict.fromkeys(problems))  # `from m import a, b` is one import
    if problems:
        pytest.fail(f"{len(problems)} {what}:\n" + "\n".join(problems), pytrace=False)


# --- checks -------------------------------------------------------------------------------------


def test_files_map_to_packages_setuptools_ships():
    """Every .py file under a package-dir folder belongs to a package listed in pyproject.toml, and
    every package is on a floor (else it would not be in the wheel, or no rule would cover it)."""
    problems = []
    listed = set(PACKAGES)
    for src in package_sources().values():
        package = src.module if src.is_package else src.module.rpartition(".")[0]
        if package not in listed:
            problems.append(f"{src.rel}:1: [packaging] in package {package}, which is not in "
                            f"[tool.setuptools] packages of pyproject.toml: the wheel would leave it out; add it")
    for package in PACKAGES:
        if package != "octolog" and floor_unit(package) == "octolog":
            problems.append(f"pyproject.toml: [floors] package {package} is on no floor: add it to KIT, STAGES "
                            f"or SHELL in tests/project/test_architecture.py (and to docs/architecture.md)")
    for unit in (*KIT, *STAGES, *SHELL):
        if unit not in listed:
            problems.append(f"tests/project/test_architecture.py: [floors] {unit} is not a package in pyproject.toml: "
                            f"update the floor tables")
    _fail(problems, "packaging problems")


def test_first_party_imports_are_under_octolog():
    """(a) `import tracker`, `from kit import bus`, `-m replay.node`: the old top-level names are gone
    everywhere, tests and bench included; only `octolog.<folder>` exists once installed."""
    problems = []
    for src in all_sources():
        for ref in refs_of(src):
            top = ref.target.split(".")[0]
            if top in OLD_TOP_LEVEL:
                new = f"octolog.{ref.target}"
                problems.append(f"{ref.where}: [namespace] {ref.kind} {ref.target!r}: there is no top-level "
                                f"{top!r} package once installed; write {new!r}")
    _fail(problems, "first-party imports outside the octolog namespace")


def _defined_names(module: ast.Module) -> set[str] | None:
    """Names bound at module level (None: anything may exist, `__getattr__` or `import *`)."""
    names: set[str] = set()
    todo: list[ast.stmt] = list(module.body)
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            if node.name == "__getattr__":
                return None
            names.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                if alias.name == "*":
                    return None
                names.add(alias.asname or alias.name.split(".")[0])
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign, ast.For, ast.With)):
            targets = (node.targets if isinstance(node, ast.Assign) else
                       [i.optional_vars for i in node.items if i.optional_vars] if isinstance(node, ast.With) else
                       [node.target])
            for target in targets:
                names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
        if isinstance(node, (ast.If, ast.Try, ast.With, ast.For, ast.While)):
            for field in ("body", "orelse", "finalbody"):
                todo += getattr(node, field, [])
            todo += [s for h in getattr(node, "handlers", []) for s in h.body]
    return names


def test_first_party_imports_resolve():
    """Every `octolog...` import names a module that exists and, for `from M import x`, a submodule or a
    name M defines: a moved module must not leave a lazy import inside a function pointing nowhere."""
    problems = []
    modules = package_sources()
    packages = set(PACKAGES)
    for src in all_sources():
        for ref in refs_of(src):
            if ref.target != "octolog" and not ref.target.startswith("octolog."):
                continue
            if ref.target not in modules and ref.target not in packages:
                problems.append(f"{ref.where}: [resolve] {ref.kind} {ref.target!r}: no such module; "
                                f"it moved or was renamed: import it from where it lives now")
                continue
            if not ref.name or ref.name == "*" or f"{ref.target}.{ref.name}" in modules or ref.target not in modules:
                continue
            names = _defined_names(parse(modules[ref.target].path))
            if names is not None and ref.name not in names:
                problems.append(f"{ref.where}: [resolve] `from {ref.target} import {ref.name}`: "
                                f"{modules[ref.target].rel} defines no {ref.name!r}; import it from where it lives now")
    _fail(problems, "first-party imports that resolve to nothing")


def test_floors():
    """(b) kit (octolog, octolog.kit, octolog.schemas) imports no stage and not the shell; a stage
    imports only the kit and itself; the shell imports anything; nothing imports octolog.__main__."""
    problems = []
    for module, src in sorted(package_sources().items()):
        unit = floor_unit(module)
        for ref in refs_of(src):
            target = imported_module(ref)
            if target is None or ref.kind == "-m":
                continue
            tunit = floor_unit(target)
            where = f"{ref.where}: [floor] {module} ({floor(unit)} {unit}) imports {target}"
            if tunit in ENTRY_POINTS:
                problems.append(f"{where}, the `python -m octolog` entry point: import octolog.shell.cli instead")
            elif floor(unit) == "kit" and floor(tunit) in ("stage", "shell"):
                problems.append(f"{where} ({floor(tunit)} {tunit}): the kit sits below every stage and the "
                                f"shell; move the code that needs {tunit} up into {tunit} (or the shell), "
                                f"or what the kit needs down into the kit")
            elif floor(unit) == "stage" and floor(tunit) == "shell":
                problems.append(f"{where} (the shell): a stage never imports the shell; move the shared code "
                                f"into octolog.kit, or the call into the shell")
            elif floor(unit) == "stage" and floor(tunit) == "stage" and tunit != unit:
                problems.append(f"{where} (another stage): stages talk over the bus and share only the kit; "
                                f"move what both need into octolog.kit or octolog.schemas, or the wiring into "
                                f"octolog.shell")
            elif floor(unit) == "unknown" or floor(tunit) == "unknown":
                problems.append(f"{where}: a module on no floor; add its package to KIT, STAGES or SHELL in "
                                f"tests/project/test_architecture.py")
    _fail(problems, "floor violations")


def _graph() -> dict[str, dict[str, Ref]]:
    """module -> {imported module: the first import of it} over the package code, all imports."""
    graph: dict[str, dict[str, Ref]] = {}
    for module, src in package_sources().items():
        edges = graph.setdefault(module, {})
        for ref in refs_of(src):
            target = imported_module(ref) if ref.kind != "-m" else None
            if target is not None and target != module:
                edges.setdefault(target, ref)
    return graph


def strongly_connected(graph: dict[str, dict[str, Ref]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module (iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
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
                    work.append((child, iter(sorted(graph.get(child, {})))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    out.append(sorted(component))
    return out


def _shortest_cycle(graph: dict[str, dict[str, Ref]], component: list[str]) -> list[str]:
    start, members = component[0], set(component)
    parent: dict[str, str] = {}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for child in sorted(graph[node]):
            if child == start:
                path = [node]
                while path[-1] != start:
                    path.append(parent[path[-1]])
                return [*reversed(path), start]
            if child in members and child not in parent:
                parent[child] = node
                queue.append(child)
    raise AssertionError(f"no cycle through {start} in {component}")


def test_strongly_connected_finds_cycles():
    """The cycle finder itself finds a circle and leaves a tree alone (a check that cannot fail is none)."""
    edges = {"a": {"b": None}, "b": {"c": None}, "c": {"a": None, "d": None}, "d": {}, "e": {"d": None}}
    assert strongly_connected(edges) == [["a", "b", "c"]]  # type: ignore[arg-type]
    assert _shortest_cycle(edges, ["a", "b", "c"]) == ["a", "b", "c", "a"]  # type: ignore[arg-type]
    assert strongly_connected({"a": {"b": None}, "b": {}}) == []  # type: ignore[dict-item]


def test_no_import_circles():
    """(c) No import circle among modules, counting lazy imports inside functions and TYPE_CHECKING
    imports: a lazy import hides a circle from Python, not from the design."""
    graph = _graph()
    problems = []
    for component in strongly_connected(graph):
        cycle = _shortest_cycle(graph, component)
        steps = [f"{a} -> {b} ({graph[a][b].where})" for a, b in pairwise(cycle)]
        problems.append(f"[circle] {len(component)} modules import each other ({', '.join(component)}); "
                        f"one cycle:\n    " + "\n    ".join(steps) +
                        "\n  fix: move what both sides need into a module neither imports (a lower floor), "
                        "or pass it in as an argument")
    _fail(problems, "import circles")


# --- the kit's layers ---------------------------------------------------------------------------

# The kit floor runs one way too (docs/architecture.md, "Floors"): the kit's basics, errors and value
# types that import nothing else of octolog, then octolog.schemas (message types, codec, topic names)
# on them, then the rest of octolog.kit (the bus, the MCAP log, the viewer, ...), which carries and
# shows schemas' messages. A lower layer never imports a higher one.
KIT_BELOW_SCHEMAS = ("octolog.kit.errors", "octolog.kit.geometry", "octolog.kit.imu", "octolog.kit.depthmodel")
KIT_LAYERS = ("the root package octolog", "the kit's basics (KIT_BELOW_SCHEMAS)", "octolog.schemas",
              "the rest of octolog.kit")


def kit_layer(module: str) -> int | None:
    """The index in KIT_LAYERS of a kit-floor module; None for a module on another floor."""
    if module == "octolog":
        return 0
    if module in KIT_BELOW_SCHEMAS:
        return 1
    unit = floor_unit(module)
    return 2 if unit == "octolog.schemas" else 3 if unit == "octolog.kit" else None


def runs_up_the_kit(module: str, target: str) -> bool:
    """`module` importing `target` goes from a lower layer of the kit to a higher one."""
    low, high = kit_layer(module), kit_layer(target)
    return low is not None and high is not None and high > low


def test_kit_layers_checker():
    """The layer check catches the circle it exists for (a check that cannot fail is none)."""
    assert runs_up_the_kit("octolog.kit.errors", "octolog.schemas.codec")  # a basic on schemas
    assert runs_up_the_kit("octolog.schemas.codec", "octolog.kit.mcaplog")  # schemas on the kit's carriers
    assert runs_up_the_kit("octolog.kit.geometry", "octolog.kit.tum")
    assert not runs_up_the_kit("octolog.kit.mcaplog", "octolog.schemas.codec")
    assert not runs_up_the_kit("octolog.schemas.codec", "octolog.kit.errors")
    assert not runs_up_the_kit("octolog.tracker.node", "octolog.kit.bus")  # another floor: test_floors


def test_kit_layers_run_one_way():
    """The kit's basics import no schemas and no other kit module; schemas imports only the basics."""
    problems = []
    modules = package_sources()
    for module in KIT_BELOW_SCHEMAS:
        if module not in modules:
            problems.append(f"tests/project/test_architecture.py: [kit layers] KIT_BELOW_SCHEMAS lists {module}, "
                            f"which does not exist: update it and docs/architecture.md")
    for module, src in sorted(modules.items()):
        for ref in refs_of(src):
            target = imported_module(ref) if ref.kind != "-m" else None
            if target is not None and runs_up_the_kit(module, target):
                low, high = KIT_LAYERS[kit_layer(module)], KIT_LAYERS[kit_layer(target)]
                problems.append(f"{ref.where}: [kit layers] {module} ({low}) imports {target} ({high}): the "
                                f"kit runs basics <- schemas <- the rest of the kit; move what {module} needs "
                                f"down, or the code that needs it up")
    _fail(problems, "imports up the kit's layers")


# --- where first-party imports sit ---------------------------------------------------------------

# The documented exception to "first-party imports sit at module top" (docs/architecture.md,
# "Floors"): the CLI's command functions import the stage they run when they run, so `octolog --help`
# does not load every stage. shell/record.py holds `octolog record`'s and `recover`'s commands next
# to the parsers cli.py imports. Each such import says what it loads in a `# lazy:` comment (on its
# line, or on a comment line above its block of imports).
LAZY_IMPORTERS = ("octolog.shell.cli", "octolog.shell.record")
LAZY = "# lazy:"


def _says_why_lazy(lines: list[str], line: int) -> bool:
    own = lines[line - 1]
    if LAZY in own and own.split(LAZY, 1)[1].strip():
        return True
    for text in (t.strip() for t in reversed(lines[:line - 1])):
        if text.startswith(LAZY):
            return bool(text[len(LAZY):].strip())
        if not text.startswith(("from ", "import ")):
            return False
    return False


def function_imports(path: Path) -> list[tuple[int, str, bool]]:
    """(line, module, says why) for each first-party import inside a function of `path`."""
    found: dict[int, str] = {}
    for fn in ast.walk(parse(path)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").split(".")[0] == "octolog"):
                found[node.lineno] = "." * node.level + (node.module or "")
            elif isinstance(node, ast.Import):
                found.update({node.lineno: a.name for a in node.names if a.name.split(".")[0] == "octolog"})
    lines = path.read_text().splitlines()
    return [(line, target, _says_why_lazy(lines, line)) for line, target in sorted(found.items())]


def test_function_imports_are_found_and_excused_only_by_a_reason(tmp_path):
    path = tmp_path / "cmds.py"
    path.write_text("import json\nfrom octolog.kit import errors\n\n"
                    "def a():\n    from octolog.tracker import node\n    import numpy\n\n"
                    "def b():\n    # lazy: the tracker stage\n    from octolog.tracker import node\n"
                    "    from octolog.tracker.config import TrackerConfig\n\n"
                    "def c():\n    import octolog.mapper.node  # lazy: the mapper stage\n"
                    "    x = 1\n    from octolog.kit import metrics\n\n"
                    "def d():\n    from octolog.kit import metrics  # lazy:\n")
    assert function_imports(path) == [(5, "octolog.tracker", False), (10, "octolog.tracker", True),
                                      (11, "octolog.tracker.config", True), (14, "octolog.mapper.node", True),
                                      (16, "octolog.kit", False), (19, "octolog.kit", False)]


def test_first_party_imports_at_module_top():
    """A first-party import inside a function hides a dependency and, often, a circle: only the
    CLI's command functions (LAZY_IMPORTERS) import that way, each saying why."""
    problems = []
    modules = package_sources()
    for module, src in sorted(modules.items()):
        for line, target, why in function_imports(src.path):
            if module not in LAZY_IMPORTERS:
                problems.append(f"{src.rel}:{line}: [lazy import] {module} imports {target} inside a function: "
                                f"move it to the top of the module (only the CLI's commands, "
                                f"{', '.join(LAZY_IMPORTERS)}, import their stage lazily)")
            elif not why:
                problems.append(f"{src.rel}:{line}: [lazy import] {target} inside a function without a reason: "
                                f"say what it would load at the top in a comment starting with {LAZY!r}, or "
                                f"move it to the top")
    problems += [f"tests/project/test_architecture.py: [lazy import] LAZY_IMPORTERS lists {m}, which does not exist"
                 for m in LAZY_IMPORTERS if m not in modules]
    _fail(problems, "first-party imports inside functions")


# --- third-party libraries with one importer -----------------------------------------------------

# Each third-party transport, log or viewer library and the one module that imports it.
ONE_IMPORTER = {"zenoh": "octolog.kit.bus.session", "mcap": "octolog.kit.mcaplog", "rerun": "octolog.kit.viz"}


def test_transport_log_and_viewer_libraries_have_one_importer():
    """zenoh only in kit/bus/session.py, mcap only in kit/mcaplog.py, rerun only in kit/viz.py."""
    problems = []
    importers: dict[str, set[str]] = {lib: set() for lib in ONE_IMPORTER}
    for module, src in sorted(package_sources().items()):
        for ref in refs_of(src):
            lib = ref.target.split(".")[0]
            if lib not in ONE_IMPORTER or ref.kind == "-m":
                continue
            importers[lib].add(module)
            if module != ONE_IMPORTER[lib]:
                problems.append(f"{ref.where}: [one importer] {module} imports {ref.target}: only "
                                f"{ONE_IMPORTER[lib]} imports {lib}; route what {module} needs through it")
    for lib, module in ONE_IMPORTER.items():
        if module not in importers[lib]:
            problems.append(f"tests/project/test_architecture.py: [one importer] {module} does not import {lib} "
                            f"(any more): update ONE_IMPORTER and docs/architecture.md")
    _fail(problems, "transport, log or viewer libraries imported outside their one module")


# --- one responsibility, and a reason where it is long ------------------------------------------

# One responsibility per module and per function (docs/architecture.md, "Floors"). Length does not
# measure that, but a long module or function is where a second one hides: over these lengths it says
# why it is one thing in a one-line `# long:` comment (a module among its lines before its first `def`
# or `class`; a function just above its `def` or among the first lines of its body).
LONG_MODULE_LINES = 800
LONG_FUNCTION_LINES = 120
LONG = "# long:"


def _reason_lines(lines: list[str], first: int, last: int) -> list[int]:
    """1-based numbers of the `# long:` comments (with a reason) among lines first..last."""
    out = []
    for n in range(max(1, first), min(len(lines), last) + 1):
        text = lines[n - 1].strip()
        if text.startswith(LONG) and text[len(LONG):].strip():
            out.append(n)
    return out


def long_parts(path: Path) -> tuple[list[tuple[int, str, int, bool]], list[int]]:
    """(line, name, length, says why) for the module (name "module") and each function of `path`
    over its length, and the lines of `# long:` comments that excuse nothing long (stale)."""
    tree, lines = parse(path), path.read_text().splitlines()
    found, claimed = [], set()
    defs = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))]
    header_end = min([d.lineno for n in defs for d in (n, *n.decorator_list)], default=len(lines) + 1) - 1
    if len(lines) > LONG_MODULE_LINES:
        why = _reason_lines(lines, 1, header_end)
        claimed.update(why)
        found.append((1, "module", len(lines), bool(why)))
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1
            if length > LONG_FUNCTION_LINES:
                first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                why = _reason_lines(lines, first - 3, first - 1) + _reason_lines(lines, node.lineno, node.lineno + 12)
                claimed.update(why)
                found.append((node.lineno, node.name, length, bool(why)))
    return found, [n for n in _reason_lines(lines, 1, len(lines)) if n not in claimed]


def test_long_parts_are_found_and_excused_only_by_a_reason(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(LONG_FUNCTION_LINES + 5))
    plain = tmp_path / "plain.py"
    plain.write_text(f"def f():\n{body}\n")
    excused = tmp_path / "excused.py"
    excused.write_text(f"{LONG} one state machine, its cases read together\ndef f():\n{body}\n")
    empty = tmp_path / "empty.py"
    empty.write_text(f"def f():\n    {LONG}\n{body}\n")
    stale = tmp_path / "stale.py"
    stale.write_text(f"def f():\n    {LONG} it was long once\n    return 1\n")
    module = tmp_path / "module.py"
    module.write_text(f'"""A module."""\n\n{LONG} one format, read and written in one place\n\n'
                      + "\n".join(f"X{i} = {i}" for i in range(LONG_MODULE_LINES)) + "\n")
    assert [(n, why) for _, n, _, why in long_parts(plain)[0]] == [("f", False)]
    assert long_parts(excused) == ([(2, "f", LONG_FUNCTION_LINES + 6, True)], [])
    assert [why for *_, why in long_parts(empty)[0]] == [False]
    assert long_parts(stale) == ([], [2])
    assert long_parts(module) == ([(1, "module", LONG_MODULE_LINES + 4, True)], [])


def test_long_modules_and_functions_say_why():
    """(d) A module over LONG_MODULE_LINES lines or a function over LONG_FUNCTION_LINES says in a
    `# long:` comment why it is one responsibility; a `# long:` comment on nothing long goes."""
    problems = []
    for module, src in sorted(package_sources().items()):
        found, stale = long_parts(src.path)
        for line, name, length, why in found:
            limit = LONG_MODULE_LINES if name == "module" else LONG_FUNCTION_LINES
            what = f"{module} has" if name == "module" else f"{name} has"
            if not why:
                problems.append(f"{src.rel}:{line}: [long] {what} {length} lines (> {limit}): if it does one "
                                f"thing, say why it is that long in a comment starting with {LONG!r}; if it "
                                f"does two, split it where they part")
        problems += [f"{src.rel}:{n}: [long] a {LONG!r} comment on nothing that long: remove it" for n in stale]
    _fail(problems, "long modules or functions without a reason")


# -- composition, not mixins -------------------------------------------------------------------------


def mixin_classes(module: ast.Module, first_party_classes: set[str]) -> list[tuple[int, str]]:
    """(line, name) of each class built from two or more first-party classes: state shared through
    `self` across classes; compose parts that own their state instead (docs/architecture.md)."""
    out = []
    for node in ast.walk(module):
        if isinstance(node, ast.ClassDef):
            bases = [b.id if isinstance(b, ast.Name) else b.attr if isinstance(b, ast.Attribute) else None
                     for b in node.bases]
            if sum(b in first_party_classes for b in bases) >= 2:
                out.append((node.lineno, node.name))
    return out


def test_mixin_finder():
    module = ast.parse("class A: pass\nclass B: pass\nclass C(A, B): pass\nclass D(A, Exception): pass\n")
    assert mixin_classes(module, {"A", "B", "C", "D"}) == [(3, "C")]


def test_no_class_is_built_from_first_party_mixins():
    sources = package_sources()
    classes = {n.name for s in sources.values() for n in ast.walk(parse(s.path)) if isinstance(n, ast.ClassDef)}
    problems = [f"{s.rel}:{line}: class {name} is built from two or more first-party classes: compose parts instead"
                for s in sources.values() for line, name in mixin_classes(parse(s.path), classes)]
    _fail(problems, "mixins")
