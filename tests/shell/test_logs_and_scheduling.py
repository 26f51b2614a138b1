"""Output fit for logs and stages that keep their share of the CPU: the status line off a terminal is
plain lines, a session says what it starts before its slow imports, a finished session keeps no empty
error records, and no stage is ranked below unrelated jobs."""

from __future__ import annotations

import io
import subprocess
import sys
from dataclasses import dataclass

import pytest
from helpers import ROOT

from octolog.shell import cli, errorfile, statusline
from octolog.shell.children import Launch, StageProcesses, launch
from octolog.shell.run import STAGES, SessionSummary, format_summary
from octolog.shell.statusline import StatusLine


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_off_a_terminal_the_status_is_a_plain_line_every_few_seconds_and_the_last_one_always():
    out, clock = io.StringIO(), Clock()
    line = StatusLine(out, tty=False, interval_s=5.0, clock=clock)
    for second in range(13):  # a state every second
        clock.now = float(second)
        line.show(f"state {second}")
    line.end()
    assert "\r" not in out.getvalue()
    assert out.getvalue().splitlines() == ["state 0", "state 5", "state 10", "state 12"]
    line.end()  # nothing held back: nothing more
    assert out.getvalue().endswith("state 12\n") and out.getvalue().count("\n") == 4


def test_on_a_terminal_the_status_is_redrawn_in_place_and_ended_once():
    out = io.StringIO()
    line = StatusLine(out, tty=True, clock=Clock())
    line.show("  100 frames, tracker 3 queued")
    line.show("  110 frames")  # shorter: padded over the longer one
    assert line.open
    line.end()
    assert out.getvalue() == "\r  100 frames, tracker 3 queued\r  110 frames" + " " * 18 + "\n"
    line.end()
    assert not line.open and out.getvalue().count("\n") == 1


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_relayed_stage_redraws_only_when_the_orchestrators_stderr_is_a_terminal(monkeypatch):
    monkeypatch.delenv(statusline.ENV, raising=False)
    assert statusline.is_terminal(FakeTty()) and not statusline.is_terminal(io.StringIO())
    # under `octolog run` the stage's stderr is a pipe; the orchestrator says where it ends up
    monkeypatch.setenv(statusline.ENV, "1")
    assert statusline.is_terminal(io.StringIO())
    monkeypatch.setenv(statusline.ENV, "0")
    assert not statusline.is_terminal(FakeTty())


@dataclass
class ReplayStatusStub:
    published: int
    total: int

    def line(self) -> str:
        return f"{self.published}/{self.total} frames"


def test_the_replays_progress_into_a_log_has_no_carriage_returns(monkeypatch, capsys):
    """Whatever the time between frames: one line per state written, each ended, the last one there."""
    monkeypatch.delenv(statusline.ENV, raising=False)
    monkeypatch.setattr(cli, "_status", None)
    for done in range(1, 31):
        cli._progress(ReplayStatusStub(done, 30))
    err = capsys.readouterr().err
    assert "\r" not in err and err.endswith("\n")
    lines = err.splitlines()
    assert lines[0] == "  10/30 frames" and lines[-1] == "  30/30 frames", lines


def test_an_error_after_a_redrawn_line_starts_a_line_of_its_own(monkeypatch, capsys):
    monkeypatch.setenv(statusline.ENV, "1")
    monkeypatch.setattr(cli, "_status", None)
    cli._progress(ReplayStatusStub(10, 30))
    cli._error_line("octolog replay: error: boom")
    assert capsys.readouterr().err == "\r  10/30 frames\noctolog replay: error: boom\n"


# The first line: printed before the orchestrator (and Zenoh, numpy, OpenCV...) is imported.
BLOCK_THE_ORCHESTRATOR = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name == "octolog.shell.run":
            raise ImportError("the test stops here")
sys.meta_path.insert(0, Block())
from octolog.shell import cli
try:
    cli.main(sys.argv[1:])
except ImportError:
    print("heavy modules loaded:", sorted(m for m in ("numpy", "zenoh", "cv2") if m in sys.modules))
"""


@pytest.mark.parametrize("command", [["run", "--source", "synthetic:5"], ["demo"]])
def test_a_session_says_what_it_starts_before_its_slow_imports(tmp_path, command):
    out = tmp_path / "s"
    proc = subprocess.run([sys.executable, "-c", BLOCK_THE_ORCHESTRATOR, *command, "--out", str(out)],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    source = "synthetic:5" if command[0] == "run" else "synthetic:150"
    assert proc.stdout.splitlines() == [
        f"octolog {command[0]}: {source} → {out} (stage logs: {out / 'logs'}); starting the stages",
        "heavy modules loaded: []"], proc.stdout + proc.stderr


def test_a_finished_run_keeps_no_empty_error_records(octolog_run):
    out, stdout = octolog_run("synthetic:30")
    assert stdout.startswith(f"octolog run: synthetic:30 → {out} ")
    assert sorted(p.name for p in (out / "logs").glob("*.log")) == ["log.log", "mapper.log", "replay.log",
                                                                     "tracker.log"]
    assert list((out / "logs").glob("*.error.json")) == []


def test_a_stage_keeps_its_reservation_while_it_runs_and_its_record_after(tmp_path):
    """The space for a record is there from before the stage starts (a full disk cannot take it);
    after the end, only a stage that recorded an error leaves its file."""
    children = StageProcesses(tmp_path)
    children.start("helped", ["--help"])  # exits 0, records nothing
    assert children.error_file("helped").read_bytes() == b" " * errorfile.RESERVED_BYTES
    children.start("failed", ["eval", str(tmp_path / "nope.txt"), str(tmp_path / "gt.txt")])  # an InputError
    for proc in children.procs.values():
        proc.wait(timeout=120)
    children.stop_all()
    assert not children.error_file("helped").exists()
    record = errorfile.read(children.error_file("failed"))
    assert record is not None and record.type == "InputError"


def test_no_stage_is_ranked_below_unrelated_jobs():
    """Under autogroup a session is a scheduling group: a niced stage in a session of its own would
    compete with unrelated jobs on a fraction of their weight. In the orchestrator's session its nice
    level only ranks it within the run; where the kernel does not group by session, a nice level
    would rank it below every other process, so none is set."""
    for name in (*STAGES, "recorder"):
        for grouped in (True, False):
            how = launch(name, grouped=grouped)
            assert how.nice >= 0
            if how.start_new_session:  # a job of its own: at the machine's common level
                assert how.nice == 0 and how.process_group is None, (name, how)
            else:  # in the run's group, leading a process group that stop_all signals whole
                assert how.process_group == 0, (name, how)
            if not grouped:
                assert how.nice == 0, (name, how)
    assert launch("mapper", grouped=True).nice > launch("tracker", grouped=True).nice  # it yields to the tracker
    assert not launch("mapper", grouped=True).start_new_session and not launch("tracker", grouped=True).start_new_session


def test_the_live_camera_is_a_job_of_its_own():
    """A starved recorder drops camera frames for good: it never shares the run's group."""
    assert launch("recorder", grouped=True) == Launch(0, start_new_session=True, process_group=None)


def test_the_run_says_what_it_finishes_once_the_frames_end(tmp_path, capsys):
    """When the frames' source ends and the tracker or the mapper still works, one line says so,
    then one every few seconds while they work (the seconds of a last adjustment and a map's files
    are not silent); `--quiet` says nothing, nor does a stage's end that leaves nothing to wait for.
    The stages' exits drive it."""
    from types import SimpleNamespace

    from octolog.shell.finishing import Finishing
    from octolog.shell.statusline import INTERVAL_S

    children = StageProcesses(tmp_path)
    children.start("replay", ["--version"])
    done: list[tuple[str, list[str]]] = []
    polls: list[list[str]] = []
    children.wait_all(lambda stage, running: done.append((stage, running)), polls.append)
    assert done == [("replay", [])] and polls and polls[0] == ["replay"]
    for plan, stage, running in ((SimpleNamespace(quiet=False, live=True), "recorder", ["log", "mapper", "tracker"]),
                                 (SimpleNamespace(quiet=False, live=False), "replay", ["log", "mapper"]),
                                 (SimpleNamespace(quiet=False, live=False), "tracker", ["log", "mapper"]),
                                 (SimpleNamespace(quiet=False, live=False), "replay", ["log"]),
                                 (SimpleNamespace(quiet=True, live=True), "recorder", ["mapper", "tracker"])):
        Finishing(children, live=plan.live, quiet=plan.quiet).done(stage, running)
    assert capsys.readouterr().err.splitlines() == [
        "octolog run: the camera stopped; finishing the tracker's last adjustment and the map and its files",
        "octolog run: the replay sent its last frame; finishing the map and its files"]
    now = [100.0]
    finishing = Finishing(children, live=True, quiet=False, clock=lambda: now[0])
    finishing.waiting(["log", "mapper", "recorder", "tracker"])  # the camera still runs: nothing
    finishing.done("recorder", ["log", "mapper", "tracker"])
    for t, running in ((101.0, ["log", "mapper", "tracker"]), (100.0 + INTERVAL_S, ["log", "mapper", "tracker"]),
                       (101.0 + INTERVAL_S, ["log", "mapper"]), (100.0 + 2 * INTERVAL_S, ["log", "mapper"]),
                       (100.0 + 4 * INTERVAL_S, ["log"])):
        now[0] = t
        finishing.waiting(running)
    assert capsys.readouterr().err.splitlines() == [
        "octolog run: the camera stopped; finishing the tracker's last adjustment and the map and its files",
        f"octolog run: still finishing the tracker's last adjustment and the map and its files ({INTERVAL_S:.0f} s "
        "since the camera stopped)",
        f"octolog run: still finishing the map and its files ({2 * INTERVAL_S:.0f} s since the camera stopped)"]


def test_the_summary_says_how_much_of_a_live_stream_the_tracker_kept_up_with(tmp_path):
    """A live run's printed summary names the frames the tracker did not take and where they stayed
    (held back by the camera, skipped by the tracker); a run that took every frame says nothing of it."""
    live = SessionSummary(out=tmp_path, source="d455:software", frames=117, frame_counts={
        "camera": 150, "published": 120, "consumed": 117, "skipped": 33, "held_back": 30})
    line = next(ln for ln in format_summary(live).splitlines() if "frames:" in ln)
    assert line == ("  frames: the tracker took 117 of the camera's 150, kept up with 78 % (30 held back by the "
                    "camera while the tracker had frames in hand; 3 skipped by the tracker)")
    paced = SessionSummary(out=tmp_path, source="mcap:x", frames=280,
                           frame_counts={"published": 294, "consumed": 280, "skipped": 14})
    assert "the tracker took 280 of the published 294, kept up with 95 % (14 skipped by the tracker)" in \
        format_summary(paced)
    whole = SessionSummary(out=tmp_path, source="tum:x", frames=294,
                           frame_counts={"published": 294, "consumed": 294, "skipped": 0})
    assert "frames:" not in format_summary(whole)
