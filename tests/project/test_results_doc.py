"""docs/results.md stays a product page: one section per capability, each reproducible.

The format docs/results.md keeps (and this test parses):
- one `## CAPABILITY` section for each of CAPABILITIES, in any order;
- each holds a markdown table, a line `Machine: ...` saying what it was measured on, and a line
  `Reproduce: `COMMAND`` (subsections may add their own `Reproduce:` lines);
- a COMMAND is `[sudo] [VAR=value ...] python bench/SCRIPT.py [--flag ...]` with SCRIPT under bench/
  and every flag one its argparse parser defines (read by AST, so no bench runs), or
  `[sudo] [VAR=value ...] python -m pytest tests/TEST.py [-k EXPR] [options]` (also `pytest ...`)
  whose -k words name tests in that file;
- no development diary: no numbered or relative development sessions or rounds, no commit hashes,
  no "must-show", no issue numbers, no "was ..., now ..." stories.
"""

from __future__ import annotations

import ast
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RESULTS_MD = ROOT / "docs" / "results.md"
CAPABILITIES = (
    "Tracker accuracy", "Tracker cost", "Fast motion", "Pipeline and live", "Mapper", "Recorder", "Transport",
    "Determinism", "Hostile input", "Fleet", "IMU",
)
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
}
_REPRODUCE = re.compile(r"^Reproduce:\s*`([^`]+)`\s*$")


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


def command_problems(command: str, root: Path = ROOT) -> list[str]:
    """What is wrong with one reproduce command: a missing script or test file, an unknown flag."""
    words = shlex.split(command)
    while words and (words[0] == "sudo" or re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", words[0])):
        words.pop(0)
    if words[:3] == ["python", "-m", "pytest"]:
        words = words[3:]
    elif words[:1] == ["pytest"]:
        words = words[1:]
    elif words[:1] == ["python"] and len(words) > 1 and words[1].startswith("bench/"):
        script = root / words[1]
        if not script.is_file():
            return [f"`{command}`: {words[1]} does not exist"]
        known = bench_flags(script)
        return [f"`{command}`: {words[1]} has no flag {w.split('=')[0]}"
                for w in words[2:] if w.startswith("-") and w.split("=")[0] not in known]
    else:
        return [f"`{command}`: want `python bench/SCRIPT.py ...` or `python -m pytest tests/TEST.py ...`"]
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
    found = sections(text)
    for name in CAPABILITIES:
        lines = found.get(name)
        if lines is None:
            problems.append(f"no `## {name}` section")
            continue
        if not any(re.match(r"^\|.*\|\s*$", line) for line in lines):
            problems.append(f"`## {name}`: no table of figures")
        if not any(line.startswith("Machine: ") for line in lines):
            problems.append(f"`## {name}`: no `Machine: ...` line saying what it was measured on")
        if not any(_REPRODUCE.match(line) for line in lines):
            problems.append(f"`## {name}`: no ``Reproduce: `COMMAND` `` line")
    for line in text.splitlines():
        if line.startswith("Reproduce:"):
            m = _REPRODUCE.match(line)
            problems += command_problems(m[1], root) if m else [f"{line!r}: want ``Reproduce: `COMMAND` ``"]
    for i, line in enumerate(text.splitlines(), 1):
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
    good = "Machine: a laptop.\n\nReproduce: `OCTOLOG_DATA=d python bench/speed.py --frames 3`\n\n| a |\n|---|\n| 1 |\n"
    text = "# Results\n\n" + "".join(f"## {name}\n\n{good}\n" for name in CAPABILITIES)
    assert doc_problems(text, tmp_path) == []
    broken = (text.replace("## Recorder", "## Recording")
              .replace("Machine: a laptop.\n\nReproduce: `OCTOLOG_DATA=d python bench/speed.py --frames 3`",
                       "Reproduce: `python bench/speed.py --fast`", 1)
              + "Reproduce: `python bench/gone.py`\n"
              + "Reproduce: `sudo python -m pytest tests/test_x.py -k three_robots -s`\n"
              + "The sixth session at commit 4b23d76 (must-show 3, issue 19): latency was 60 ms, now 30 ms.\n")
    problems = "\n".join(doc_problems(broken, tmp_path))
    for expected in ("no `## Recorder` section", "no `Machine:", "has no flag --fast", "bench/gone.py does not exist",
                     "-k 'three_robots' matches no test", "a development session", "a commit-hash-like token",
                     "a must-show", "an issue number", "a commit (", "a was/now story"):
        assert expected in problems, f"{expected!r} not reported in:\n{problems}"


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
