"""The docs' command tour: every `octolog` command line in README.md and docs/*.md, as written, on
short inputs, so a documented command that stops working fails here.

The tour works in a folder laid out like a checkout beside `../shared`: its `../shared/data` holds the
first 40 frames of TUM fr1/xyz under the documented folder name and the RealSense bags. Lines run in
the order the docs give them; a line reads its inputs from the lines before it (`out/fr1xyz`, ...).
"Short inputs" is the only change to a line: fewer synthetic frames, a 1 s camera, a later start
within the short TUM folder, the docs' `tum:PATH` placeholder filled. What a line cannot do here is
named in one place each:

- a real D455 (`--source d455`, `record` without `--backend software`): the line runs and must fail
  with the one-line "no camera" error that names the simulated camera;
- other hosts, a router started apart, TLS certificates or a fleet's shards (`--connect`, `--router`,
  `router`, `stitch`): the line is parsed by the real parser and its `--set` values checked by the
  command's config (unless it names a `--config` file of the reader's), not run;
- inputs the docs leave to the reader (`killed.mcap`, `out/day2-apart`, `out/demo`): made first by
  the tour, with octolog itself.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import ROOT, tum_first300

from octolog.kit.errors import ConfigError

DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
TUM_DOC_PATH = "../shared/data/tum/rgbd_dataset_freiburg1_xyz_first300"
TOUR_FRAMES = 20  # frames of the short TUM folder and at most of a synthetic source
NO_CAMERA = "no RealSense device found"

# short inputs: (pattern, replacement) applied to every line before it runs
SHORTER = [
    (r"tum:PATH", f"tum:{TUM_DOC_PATH}"),
    (r"--duration \d+", "--duration 1"),  # the simulated camera renders 1 s + 1 s of frames
    (r"synthetic:(\d+)", lambda m: f"synthetic:{min(int(m.group(1)), TOUR_FRAMES)}"),
    (r"blank=[\d.]+\+[\d.]+", "blank=0.5+0.3"),
    (r"replay\.start=\d+", f"replay.start={TOUR_FRAMES // 2}"),
]
# lines that need another host, a router started apart, TLS certificates or a fleet's shards:
# parsed, not run
ELSEWHERE = re.compile(r"--connect |--router |^octolog router |^octolog stitch ")
# lines that need a real D455
CAMERA = re.compile(r"--source d455(\s|$)|^octolog record (?!.*--backend software)")


def documented() -> list[tuple[str, str]]:
    """(file name, command line) of every `octolog` line in the docs' code blocks, continuation lines
    joined, comments dropped, in the docs' order."""
    out = []
    for path in DOCS:
        for block in re.findall(r"```[a-z0-9]*\n(.*?)```", path.read_text(), re.S):
            for line in re.sub(r"\\\n\s*", " ", block).splitlines():
                line = line.strip().removeprefix("$ ")
                if line.startswith("octolog "):
                    out.append((path.name, shlex.join(shlex.split(line, comments=True))))
    return out


def shorter(line: str) -> str:
    for pattern, replacement in SHORTER:
        line = re.sub(pattern, replacement, line)
    return line


def _short_tum(src: Path, dst: Path, n: int) -> None:
    """The first `n` colour frames of a TUM folder, with their depth, truth and accelerometer spans."""
    def rows(name: str) -> list[str]:
        path = src / name
        return [r for r in path.read_text().splitlines() if r and not r.startswith("#")] if path.exists() else []

    rgb = rows("rgb.txt")[:n]
    end = float(rgb[-1].split()[0]) + 0.05
    dst.mkdir(parents=True)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "accelerometer.txt"):
        kept = rgb if name == "rgb.txt" else [r for r in rows(name) if float(r.split()[0]) <= end]
        if kept:
            (dst / name).write_text("\n".join(kept) + "\n")
    for name in ("rgb.txt", "depth.txt"):
        for row in (dst / name).read_text().splitlines():
            image = row.split()[1]
            (dst / image).parent.mkdir(exist_ok=True)
            (dst / image).symlink_to(src / image)


@pytest.fixture(scope="module")
def checkout(tmp_path_factory) -> Path:
    """A working folder beside a `../shared/data` of short inputs."""
    tum = tum_first300()
    base = tmp_path_factory.mktemp("tour")
    data = base / "shared" / "data"
    _short_tum(tum, data / "tum" / tum.name, TOUR_FRAMES)
    (data / "realsense").mkdir()
    for bag in (tum.parents[1] / "realsense").glob("*.bag"):
        (data / "realsense" / bag.name).symlink_to(bag)
    (base / "main").mkdir()
    return base / "main"


def _octolog(cwd: Path, line: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "RERUN_DISABLE_ANALYTICS": "1"}
    return subprocess.run([sys.executable, "-m", "octolog", *shlex.split(line)[1:]], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def _prepare(cwd: Path, line: str) -> None:
    """What a line reads that the docs leave to the reader, made with octolog itself."""
    if line.startswith("octolog recover killed.mcap"):  # a recording cut off mid-chunk
        whole = (cwd / "out" / "fr1xyz" / "session.mcap").read_bytes()
        (cwd / "killed.mcap").write_bytes(whole[: len(whole) * 2 // 3])
    elif "out/day2-apart" in line:  # the same place, tracked on its own
        assert _octolog(cwd, shorter("octolog run --source tum:PATH --set replay.start=20 --rerun off "
                                     "--out out/day2-apart")).returncode == 0
    elif "out/demo/" in line:
        assert _octolog(cwd, f"octolog demo --frames {TOUR_FRAMES} --rerun off").returncode == 0


def _parses(line: str) -> None:
    """The line's options exist and its `--set` values pass the command's config (with the reader's
    own `--config` file, which the tour does not have, the options only)."""
    from octolog.kit.config import load
    from octolog.mapper.config import MapperConfig
    from octolog.recorder.config import RecorderConfig
    from octolog.replay.config import ReplayConfig
    from octolog.shell.cli import build_parser
    from octolog.tracker.config import TrackerConfig

    argv = shlex.split(line)[1:]
    args = build_parser().parse_args(argv)
    configs = {"map": (MapperConfig, "mapper"), "track": (TrackerConfig, "tracker"),
               "replay": (ReplayConfig, "replay"), "record": (RecorderConfig, "recorder")}
    if argv[0] in configs and getattr(args, "set", None) and not getattr(args, "config", None):
        cls, section = configs[argv[0]]
        load(cls, None, args.set, section=section, own=True)


def test_the_docs_hold_commands_the_tour_reads():
    """The extraction itself: the README's quick start is found, continuation lines are joined and
    comments are dropped (a tour that read nothing would pass whatever the docs said)."""
    lines = [line for _, line in documented()]
    assert len(lines) >= 30
    assert f"octolog run --source tum:{TUM_DOC_PATH} --out out/fr1xyz" in lines
    assert any("--set replay.rate=1.0 --set tracker.live=true" in line for line in lines)
    assert not any("#" in line for line in lines)
    assert shorter("octolog run --source synthetic:600:motion=turns --duration 60") == \
        f"octolog run --source synthetic:{TOUR_FRAMES}:motion=turns --duration 1"
    _parses("octolog map --connect tcp/HOST:7447 --set publish_every=5 --out out/map")
    with pytest.raises(SystemExit):
        _parses("octolog map --connect tcp/HOST:7447 --no-such-option")
    with pytest.raises(ConfigError, match="no_such_key"):
        _parses("octolog map --connect tcp/HOST:7447 --set no_such_key=1")


def test_every_documented_command_works_as_written(checkout):
    """Each line in turn: run lines exit 0 without a traceback, camera lines fail in one line naming
    the simulated camera, elsewhere lines parse. All failures are reported together."""
    failures = []
    for doc, line in documented():
        if ELSEWHERE.search(line):
            try:
                _parses(line)
            except (SystemExit, Exception) as exc:  # noqa: BLE001  (reported with the line)
                failures.append(f"{doc}: {line}\n  does not parse: {exc!r}")
            continue
        _prepare(checkout, line)
        proc = _octolog(checkout, shorter(line))
        if CAMERA.search(line):
            ok = proc.returncode == 1 and NO_CAMERA in proc.stderr and "software" in proc.stderr \
                and len(proc.stderr.strip().splitlines()) == 1
        else:
            ok = proc.returncode == 0 and "Traceback" not in proc.stderr
        if not ok:
            failures.append(f"{doc}: {shorter(line)}\n  exit {proc.returncode}: {proc.stderr.strip()[-600:]}")
    assert not failures, "\n".join(failures)
