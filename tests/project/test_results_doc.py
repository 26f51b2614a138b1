"""docs/results.md stays a product page: short, its headline tables each with the command that measures them.

The format docs/results.md keeps (and this test parses):
- at most MAX_LINES lines; before the first `##`, a short intro with a line `Machine: ...` saying what
  the figures were measured on;
- the `## SECTION`s of SECTIONS, in that order; each but `## Known limits` holds at least one
  markdown table (subsections `###` may split a section);
- every table has a line `Reproduce: `COMMAND`` right above or right below it (only blank lines
  between), so a reader can run what produced it; the detail stays in the bench's own output;
- a COMMAND is `[sudo] [VAR=value ...] PYTHON bench/SCRIPT.py [--flag ...]` (PYTHON: `python`,
  `python3` or `.venv/bin/python`) with SCRIPT under bench/ and every flag one its argparse parser
  defines (read by AST, so no bench runs); or `[sudo] [VAR=value ...] PYTHON -m pytest tests/TEST.py
  [-k EXPR] [options]` (also `pytest ...`) whose -k words name tests in that file; or `make TARGET`
  with TARGET a rule of the Makefile. A command quoted inline in the prose (a code span starting
  with one of those interpreters) is checked the same way;
- no development diary: no numbered or relative development sessions or rounds, no commit hashes,
  no "must-show", no issue numbers, no "was ..., now ..." stories, no "before → now" or
  "previous release" columns: every comparison is one the bench runs side by side.
"""

from __future__ import annotations

import ast
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RESULTS_MD = ROOT / "docs" / "results.md"
MAX_LINES = 400
SECTIONS = ("Accuracy", "Speed", "Live figures", "Fleet", "Maps", "Known limits")
WITHOUT_TABLE = {"Known limits"}
REFERENCES = {"Accuracy": ("ORB-SLAM3", "RTAB-Map")}  # what a section compares against, by name
PYTHONS = {"python", "python3", ".venv/bin/python"}
PYTEST_OPTIONS = {"-s", "-q", "-x", "-v", "-k", "--hypothesis-show-statistics"}
_ORDINAL = (r"first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|"
            r"thirteenth|fourteenth|fifteenth|this|last|next|previous|earlier|later")
DIARY = {
    "a development session or round": re.compile(rf"\b(?:{_ORDINAL})\s+(?:sessions?|rounds?)\b", re.I),
    "a numbered session": re.compile(r"\bsessions?\s+\d+\b", re.I),
    "a must-show": re.compile(r"\bmust[- ]shows?\b", re.I),
    "an issue number": re.compile(r"\bissues?\s+#?\d+\b", re.I),
    "a commit": re.compile(r"\b(?:commit(?:s|ted)?|uncommitted)\b", re.I),
    "a commit-hash-like token": re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"),
    "a was/now story": re.compile(r"\bwas\b[^.\n]{0,80}\bnow\b|\bpreviously\b|\bused to\b", re.I),
    "a before/now comparison with code a reader cannot run":
        re.compile(r"\bbefore\b[^|\n]{0,3}(?:→|->)|\bprevious (?:release|version)s?\b", re.I),
}
_REPRODUCE = re.compile(r"^Reproduce:\s*`([^`]+)`\s*$")
_TABLE_ROW = re.compile(r"^\|.*\|\s*$")
_INLINE_COMMAND = re.compile(r"^(?:sudo\s+)?(?:[A-Z_][A-Z0-9_]*=\S*\s+)*(?:\.venv/bin/python|python3?|pytest)\s")


def sections(text: str) -> dict[str, list[str]]:
    """`## heading` -> its lines (subsections included)."""
    out: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in text.splitlines():
        m = re.match(r"^##\s+(.*?)\s*$", line)
        if m and not line.startswith("###"):
            current = out.setdefault(m[1], [])
        elif re.match(r"^#\s", line):
            current = None
        elif current is not None:
            current.append(line)
    return out


def tables(lines: list[str]) -> list[tuple[int, int]]:
    """(first, last) line index of each markdown table: a run of `| ... |` lines."""
    out: list[tuple[int, int]] = []
    for i, line in enumerate(lines):
        if _TABLE_ROW.match(line):
            if out and out[-1][1] == i - 1:
                out[-1] = (out[-1][0], i)
            else:
                out.append((i, i))
    return out


def next_text(lines: list[str], i: int, step: int) -> str:
    """The first non-blank line from i on, going by step (-1 up, +1 down); "" when there is none."""
    while 0 <= i < len(lines):
        if lines[i].strip():
            return lines[i]
        i += step
    return ""


def bench_flags(script: Path) -> set[str]:
    """The long and short flags a bench script's argparse defines, read from its `add_argument` calls."""
    flags: set[str] = set()
    for node in ast.walk(ast.parse(script.read_text(), str(script))):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
            flags.update(a.value for a in node.args
                         if isinstance(a, ast.Constant) and isinstance(a.value, str) and a.value.startswith("-"))
    return flags | {"-h", "--help"}


def names_of_tests(test_file: Path) -> set[str]:
    tree = ast.parse(test_file.read_text(), str(test_file))
    return {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
            and n.name.startswith("test")}


def make_targets(root: Path) -> set[str]:
    makefile = root / "Makefile"
    if not makefile.is_file():
        return set()
    return {t for m in re.finditer(r"^([\w.-]+(?:[ \t]+[\w.-]+)*)[ \t]*:(?!=)", makefile.read_text(), re.M)
            for t in m[1].split()}


def command_problems(command: str, root: Path = ROOT) -> list[str]:
    """What is wrong with one reproduce command: a missing script, test file or make target, an unknown flag."""
    words = shlex.split(command)
    while words and (words[0] == "sudo" or re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", words[0])):
        words.pop(0)
    if words[:1] == ["make"]:
        unknown = [w for w in words[1:] if not w.startswith("-") and "=" not in w and w not in make_targets(root)]
        return [f"`{command}`: the Makefile has no target {w}" for w in unknown] or (
            [] if len(words) > 1 else [f"`{command}`: make without a target"])
    if words[:1] and words[0] in PYTHONS and words[1:3] == ["-m", "pytest"]:
        words = words[3:]
    elif words[:1] == ["pytest"]:
        words = words[1:]
    elif words[:1] and words[0] in PYTHONS and len(words) > 1 and words[1].startswith("bench/"):
        script = root / words[1]
        if not script.is_file():
            return [f"`{command}`: {words[1]} does not exist"]
        known = bench_flags(script)
        return [f"`{command}`: {words[1]} has no flag {w.split('=')[0]}"
                for w in words[2:] if w.startswith("-") and w.split("=")[0] not in known]
    else:
        return [f"`{command}`: want `python bench/SCRIPT.py ...`, `python -m pytest tests/TEST.py ...` "
                f"or `make TARGET`"]
    if not words or not words[0].startswith("tests/"):
        return [f"`{command}`: pytest without a tests/ file"]
    test_file = root / words[0]
    if not test_file.is_file():
        return [f"`{command}`: {words[0]} does not exist"]
    problems = [f"`{command}`: pytest option {w} not known to this check (add it to PYTEST_OPTIONS if real)"
                for w in words[1:] if w.startswith("-") and w not in PYTEST_OPTIONS]
    if "-k" in words:
        expr = words[words.index("-k") + 1]
        names = names_of_tests(test_file)
        for word in re.findall(r"\w+", expr):
            if word not in {"and", "or", "not"} and not any(word in n for n in names):
                problems.append(f"`{command}`: -k {word!r} matches no test in {words[0]}")
    return problems


def doc_problems(text: str, root: Path = ROOT) -> list[str]:
    problems = []
    lines = text.splitlines()
    if len(lines) > MAX_LINES:
        problems.append(f"{len(lines)} lines, more than {MAX_LINES}: keep the headline rows, leave the detail "
                        f"to the bench's output")
    intro = lines[:next((i for i, line in enumerate(lines) if line.startswith("## ")), len(lines))]
    if not any(line.startswith("Machine: ") for line in intro):
        problems.append("no `Machine: ...` line in the intro saying what the figures were measured on")
    found = sections(text)
    order = [name for name in found if name in SECTIONS]
    for name in SECTIONS:
        body = found.get(name)
        if body is None:
            problems.append(f"no `## {name}` section")
            continue
        if name not in WITHOUT_TABLE and not tables(body):
            problems.append(f"`## {name}`: no table of figures")
        for reference in REFERENCES.get(name, ()):
            if reference not in "\n".join(body):
                problems.append(f"`## {name}`: no comparison with {reference}")
    if order != [name for name in SECTIONS if name in found]:
        problems.append(f"sections in the order {order}, want {list(SECTIONS)}")
    for first, last in tables(lines):
        if not any(_REPRODUCE.match(next_text(lines, i, step)) for i, step in ((first - 1, -1), (last + 1, 1))):
            problems.append(f"line {first + 1}: a table without a ``Reproduce: `COMMAND` `` line right above "
                            f"or below it: {lines[first][:60]!r}")
    for i, line in enumerate(lines, 1):
        if line.startswith("Reproduce:"):
            m = _REPRODUCE.match(line)
            problems += command_problems(m[1], root) if m else [f"line {i}: want ``Reproduce: `COMMAND` ``"]
        else:
            for span in re.findall(r"`([^`\n]+)`", line):
                if _INLINE_COMMAND.match(span + " "):
                    problems += [f"line {i}: {p}" for p in command_problems(span, root)]
        for what, pattern in DIARY.items():
            for m in pattern.finditer(line):
                problems.append(f"line {i}: {what} ({m[0]!r}): say what the code does and measures now")
    return problems


def test_results_doc_is_a_product_page():
    problems = doc_problems(RESULTS_MD.read_text())
    if problems:
        pytest.fail("docs/results.md:\n" + "\n".join(problems), pytrace=False)


def test_the_check_catches_what_it_should(tmp_path):
    """A made-up page with each kind of fault: every fault is reported."""
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "speed.py").write_text(
        "import argparse\nap = argparse.ArgumentParser()\nap.add_argument('--frames', type=int)\n")
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_x.py").write_text("def test_two_robots():\n    pass\n")
    (tmp_path / "Makefile").write_text("bench: setup\n\tpython bench/speed.py\n")
    good = "Reproduce: `OCTOLOG_DATA=d .venv/bin/python bench/speed.py --frames 3`\n\n| a |\n|---|\n| 1 |\n"
    below = "| b |\n|---|\n| 2 |\n\nReproduce: `make bench`\n"
    text = ("# Results\n\nMachine: a laptop.\n\n"
            + "".join(f"## {name}\n\n{good}\n{below}\n" for name in SECTIONS)
            + "Inline: `python bench/speed.py --frames 2`.\n").replace(
        "## Accuracy\n", "## Accuracy\n\nAgainst ORB-SLAM3 and RTAB-Map.\n")
    assert doc_problems(text, tmp_path) == []
    broken = (text.replace("## Fleet", "## Robots")
              .replace("Machine: a laptop.", "On a laptop.")
              .replace("Reproduce: `make bench`", "Reproduce: `make benchmark`", 1)
              .replace(good, good.replace("--frames 3", "--fast"), 1)
              .replace(good, "| c |\n|---|\n| 3 |\n\nSome words.\n\n" + good, 1)
              + "Reproduce: `python bench/gone.py`\n"
              + "Reproduce: `sudo python -m pytest tests/test_x.py -k three_robots -s`\n"
              + "Inline: `.venv/bin/python bench/slow.py`.\n"
              + "| session | ms: before → now |\n|---|---|\n| a | 2 → 1 |\n"
              + "The sixth session at commit 4b23d76 (must-show 3, issue 19): latency was 60 ms, now 30 ms.\n"
              + "\n".join(["filler"] * MAX_LINES))
    problems = "\n".join(doc_problems(broken, tmp_path))
    for expected in ("no `## Fleet` section", "no `Machine:", "has no flag --fast", "bench/gone.py does not exist",
                     "the Makefile has no target benchmark", "bench/slow.py does not exist",
                     "-k 'three_robots' matches no test", "a table without a ``Reproduce", "more than 400",
                     "a development session", "a commit-hash-like token", "a must-show", "an issue number",
                     "a commit (", "a was/now story", "a before/now comparison"):
        assert expected in problems, f"{expected!r} not reported in:\n{problems}"
    assert problems.count("a table without") == 2  # the inserted table and the trailing before/now one
    assert "no comparison with RTAB-Map" in "\n".join(doc_problems(text.replace("RTAB-Map", "X"), tmp_path))


# The other docs describe the code, so they may show ids and hashes (a publisher id, a probe's
# output) and tell a reader to commit; the story words are out everywhere. Code spans are quoted
# text (an error message may say "this session"), so they are left out.
STORY = {what: DIARY[what] for what in ("a development session or round", "a numbered session", "a must-show",
                                        "an issue number", "a was/now story")}


def story_problems(text: str, where: str) -> list[str]:
    problems = []
    for i, line in enumerate(text.splitlines(), 1):
        prose = re.sub(r"`[^`]*`", "``", line)
        for what, pattern in STORY.items():
            problems += [f"{where}:{i}: {what} ({m[0]!r})" for m in pattern.finditer(prose)]
    return problems


def test_no_development_story_in_the_other_docs():
    docs = [p for p in sorted((ROOT / "docs").glob("*.md")) if p != RESULTS_MD] + [ROOT / "README.md"]
    problems = [p for doc in docs for p in story_problems(doc.read_text(), str(doc.relative_to(ROOT)))]
    assert len(story_problems("In the ninth session (issue 18, must-show 2) it was slow, now fast.", "x")) == 4
    assert story_problems("It prints `this session ...` when killed.", "x") == []
    if problems:
        pytest.fail("docs that say what happened instead of what is:\n" + "\n".join(problems), pytrace=False)
