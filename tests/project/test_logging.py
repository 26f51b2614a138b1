"""The library logs, the CLI prints: no `print` below the shell, and a stage's log lines are plain
text that name the stage (kit/logs.py), Rerun's own included."""

from __future__ import annotations

import ast
import io
import logging
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from octolog.kit import logs

ROOT = Path(__file__).resolve().parents[2]
# the kit and the stages: library code, which logs (shell/ and octolog/__main__.py are the CLI)
LIBRARY = ("kit", "schemas", "recorder", "replay", "tracker", "mapper")
ANSI = re.compile(r"\x1b\[")
LINE = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z (\S+) ([A-Z]+) (\S+): (.*)$")


def builtin_prints(source: str) -> list[int]:
    """Line numbers of calls to the builtin `print` in `source` (none if the module binds `print` itself)."""
    tree = ast.parse(source)
    bound = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom) for a in n.names}
    bound |= {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)}
    if "print" in bound:
        return []
    return [n.lineno for n in ast.walk(tree)
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "print"]


def test_the_print_finder_finds_prints():
    assert builtin_prints("import sys\n\ndef f():\n    print('x', file=sys.stderr)\n") == [4]
    assert builtin_prints("log.warning('x')\nf(print)\nself.print('x')\n") == []


def test_no_print_outside_the_cli():
    modules = [p for d in LIBRARY for p in sorted((ROOT / d).rglob("*.py"))] + [ROOT / "octolog" / "__init__.py"]
    assert len(modules) > 50
    found = [f"{p.relative_to(ROOT)}:{n}" for p in modules for n in builtin_prints(p.read_text())]
    assert not found, ("library code prints; log instead (logging.getLogger(__name__)), the CLI alone prints: "
                       + ", ".join(found))


def test_a_record_is_one_plain_line_naming_the_stage(monkeypatch):
    monkeypatch.delenv("NO_COLOR", raising=False)
    out = io.StringIO()
    log = logging.getLogger("octolog.tracker.node")
    with logs.configured("tracker", "info", stream=out):
        assert logs.level() == "info"
        log.debug("not shown")
        log.info("frame %d", 7)
        log.warning("camera reads out in %g ms", 5.0)
        log.warning("from another bus", extra={"stage": "placement"})
        logging.getLogger("somelib").info("not shown: other libraries from warning up")
    log.warning("after the block: not on this stream")
    lines = out.getvalue().splitlines()
    assert [LINE.match(ln).groups() for ln in lines] == [  # type: ignore[union-attr]
        ("tracker", "INFO", "octolog.tracker.node", "frame 7"),
        ("tracker", "WARNING", "octolog.tracker.node", "camera reads out in 5 ms"),
        ("placement", "WARNING", "octolog.tracker.node", "from another bus"),
    ]
    assert logs.level() == logs.DEFAULT_LEVEL
    assert os.environ.get("NO_COLOR") == "1"  # not a terminal: Rust's loggers write no colour either


def test_the_level_comes_from_the_command_line():
    from octolog.shell.args import command_logging
    from octolog.shell.cli import build_parser

    args = build_parser().parse_args(["track", "--log-level", "error"])
    assert args.log_level == "error"
    with command_logging(args) as handler:
        assert logging.getLogger("octolog").getEffectiveLevel() == logging.ERROR
        record = logging.LogRecord("octolog.x", logging.ERROR, __file__, 1, "m", None, None)
        assert handler.filter(record) and record.stage == "tracker"  # type: ignore[attr-defined]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["track", "--log-level", "loud"])
    assert build_parser().parse_args(["eval", "a", "b"]).log_level == "warning"


def test_rerun_warnings_in_a_log_file_are_plain(tmp_path):
    """A stage whose stderr is a file (as `octolog run` gives each stage logs/STAGE.log): Rerun's own
    warning (an entity path it cannot parse) reaches the file without ANSI colour codes."""
    script = textwrap.dedent("""
        from octolog.kit import logs

        with logs.configured("tracker"):
            from octolog.kit.viz import Viz

            with Viz("save:" + __import__("sys").argv[1], "tracker", "id") as viz:
                viz.rec.log("a/b\\\\q", viz._rr.Points3D([[0.0, 0.0, 0.0]]))
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("NO_COLOR", "RUST_LOG")}
    with open(tmp_path / "tracker.log", "wb") as log:
        subprocess.run([sys.executable, "-c", script, str(tmp_path)], stdout=log, stderr=log, env=env,
                       check=True, timeout=120)
    text = (tmp_path / "tracker.log").read_text()
    assert "Unknown escape sequence" in text, text
    assert not ANSI.search(text), text
