"""A stage's known error reaches `octolog run` as a typed record, and stage failures have types."""

from __future__ import annotations

from pathlib import Path

import pytest

from octolog.kit.errors import InputError, StageExited, StageFailed, StageKilled
from octolog.shell import cli, errorfile
from octolog.shell.children import StageProcesses


def test_a_known_error_is_recorded_for_the_orchestrator(tmp_path, monkeypatch, capsys):
    record = tmp_path / "eval.error.json"
    monkeypatch.setenv(errorfile.ENV, str(record))
    assert cli.main(["eval", str(tmp_path / "nope.txt"), str(tmp_path / "gt.txt")]) == 1
    line = capsys.readouterr().err.strip()
    got = errorfile.read(record)
    assert got is not None and got.type == "InputError"
    assert line == f"octolog eval: error: {got.message}"


def test_no_record_without_the_variable_or_for_a_success(tmp_path, monkeypatch):
    monkeypatch.delenv(errorfile.ENV, raising=False)
    errorfile.write(InputError("x"))  # not a stage of `octolog run`: nothing written anywhere
    assert errorfile.read(tmp_path / "missing.json") is None
    (tmp_path / "bad.json").write_text("[1, 2]")
    assert errorfile.read(tmp_path / "bad.json") is None


def test_stage_failures_are_typed_and_name_the_stage(tmp_path):
    children = StageProcesses(tmp_path)
    (tmp_path / "tracker.log").write_text("frame 10\nTraceback (most recent call last):\nValueError: boom\n\n")
    assert children.reason("tracker") == "ValueError: boom"  # no record: the log's last line
    children.error_file("tracker").write_text('{"type": "MapError", "message": "cannot write map.bt"}')
    assert children.reason("tracker") == "cannot write map.bt"
    killed = StageKilled("tracker", 9, "x", "t.log")
    exited = StageExited("replay", 1, "bad image", "r.log")
    assert str(killed) == "the tracker stage killed by signal 9: x (log: t.log)" and killed.signal == 9
    assert str(exited) == "the replay stage exited with code 1: bad image (log: r.log)" and exited.code == 1
    for exc in (killed, exited):
        with pytest.raises(StageFailed):
            raise exc


def test_a_stop_that_a_library_turns_into_its_own_error_is_an_interruption(monkeypatch, capsys):
    """SIGTERM raises KeyboardInterrupt wherever the stage is; inside open3d's import that comes out as
    ImportError("initialization failed"): still a stop (exit 130, one line), not a traceback. Any
    other error is not swallowed."""
    import argparse

    def stopped_in_an_import(args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise ImportError("initialization failed") from exc

    def broken(args):
        raise ImportError("no module named x")

    assert cli._run_command(argparse.Namespace(command="replay", func=stopped_in_an_import)) == 130
    assert capsys.readouterr().err == "octolog replay: interrupted\n"
    with pytest.raises(ImportError, match="no module named x"):
        cli._run_command(argparse.Namespace(command="replay", func=broken))


def test_a_reader_that_goes_away_stops_the_command_quietly(tmp_path):
    """`octolog info SESSION | head`: the pipe closes before the command writes (here: closed from
    the start); no traceback, exit 1."""
    import os
    import subprocess
    import sys

    from octolog.shell.sessiondir import INCOMPLETE

    (tmp_path / INCOMPLETE).write_text("the tracker stage exited with code 1\n")
    read, write = os.pipe()
    os.close(read)
    try:
        proc = subprocess.run([sys.executable, "-m", "octolog", "info", str(tmp_path)], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write)
    assert proc.returncode == 1 and proc.stderr == "", proc.stderr


def test_a_second_stop_while_stopping_is_said_and_ignored(monkeypatch, capsys):
    """Ctrl-C / SIGTERM: the first unwinds (KeyboardInterrupt), one more while that runs is said on
    stderr and ignored, so the stop finishes instead of ending in a traceback."""
    monkeypatch.setattr(cli, "_stopping", False)
    with pytest.raises(KeyboardInterrupt):
        cli._terminate(2, None)
    assert cli._terminate(2, None) is None
    assert capsys.readouterr().err == "octolog: stopping already; finishing what was written\n"



def test_messages_name_the_problem_once(tmp_path, capsys):
    """One line, one prefix, the real cause: `merge` of one session, `view` of a folder that is not
    there, `eval --max-dt` of no window."""
    (tmp_path / "a").mkdir()
    assert cli.main(["merge", str(tmp_path / "a"), "--out", str(tmp_path / "m")]) == 1
    assert capsys.readouterr().err == "octolog merge: error: give two sessions or more\n"
    assert cli.main(["view", str(tmp_path / "nope")]) == 1
    assert capsys.readouterr().err == f"octolog view: error: {tmp_path / 'nope'}: no such session folder\n"
    with pytest.raises(SystemExit) as stop:
        cli.main(["eval", "a.txt", "b.txt", "--max-dt", "-1"])
    assert stop.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == ("octolog eval: error: argument --max-dt: -1: want a window of "
                                                        "more than 0 seconds")


def test_version_and_help_texts_say_what_the_commands_take(capsys):
    """`octolog --version`; `info` says it reads sessions and maps too; `router --listen` says what it is."""
    from octolog import __version__

    with pytest.raises(SystemExit) as stop:
        cli.main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out == f"octolog {__version__}\n"
    for argv, want in ((["info", "--help"], "a session folder, an MCAP"), (["router", "--help"], "where stages and robots"),
                       (["track", "--help"], "--rerun SPEC off (default), save:DIR"),
                       (["replay", "--help"], "off (default; re-running a SESSION: save into OUT/rerun)")):
        with pytest.raises(SystemExit):
            cli.main(argv)
        assert want in " ".join(capsys.readouterr().out.split()), argv


def test_replay_of_a_file_points_to_the_command_that_takes_it(tmp_path, capsys):
    """`octolog replay SESSION/session.mcap` and `octolog replay RECORDING.mcap`: one line naming
    what the file is and the command for it, before anything starts."""
    session = tmp_path / "s"
    session.mkdir()
    (session / "config.toml").write_text("")
    (session / "session.mcap").write_bytes(b"")
    (tmp_path / "r.mcap").write_bytes(b"")
    assert cli.main(["replay", str(session / "session.mcap")]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"octolog replay: error: {session / 'session.mcap'}: a session's log, not its folder; "
                          f"`octolog replay {session}` re-runs") and err.count("\n") == 1, err
    assert cli.main(["replay", str(tmp_path / "r.mcap")]) == 1
    assert f"`octolog run --source mcap:{tmp_path / 'r.mcap'}`" in capsys.readouterr().err


def test_info_of_an_mcap_holding_only_its_header_is_an_error(tmp_path, capsys):
    """docs/cli.md: an MCAP with no readable record is an error; a header alone (a recorder killed
    before its first message) says nothing of what was recorded."""
    from mcap.writer import Writer

    path = tmp_path / "header.mcap"
    with open(path, "wb") as f:
        Writer(f).start(profile="ros2", library="test")  # never finished: magic and header only
    assert cli.main(["info", str(path)]) == 1
    assert capsys.readouterr().err.startswith(f"octolog info: error: {path}: no readable MCAP records after the header")


def test_stages_of_a_run_killed_outright_finish_their_files_and_stop(tmp_path):
    """`octolog run` killed with SIGKILL cannot stop its stages: each notices its run is gone, stops as
    if interrupted and leaves a readable session log instead of running on for peers that are gone."""
    import os
    import select
    import signal
    import subprocess
    import sys

    from helpers import ROOT, read_until

    from octolog.kit.mcaplog import summarize

    out = tmp_path / "s"
    run = subprocess.Popen([sys.executable, "-m", "octolog", "run", "--source", "synthetic:3000", "--rerun", "off",
                            "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    read_until(run, "starting the stages")
    read_until(run, " frames ")  # the replay's status line: the stages are up and working
    stages = [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit() and _cmdline_has(p, str(out))
              and int(p.name) != run.pid]
    assert len(stages) >= 4, stages
    run.send_signal(signal.SIGKILL)
    run.wait()
    for pid in stages:  # each pid's end is an event (pidfd): nothing here sleeps
        try:
            fd = os.pidfd_open(pid)
        except ProcessLookupError:
            continue
        ready, _, _ = select.select([fd], [], [], 120)
        os.close(fd)
        assert ready, f"stage {pid} still running 120 s after its run was killed"
    assert summarize(out / "session.mcap").topics  # finished: a summary section, readable
    assert "interrupted" in (out / "logs" / "tracker.log").read_text()


def _cmdline_has(proc: Path, text: str) -> bool:
    try:
        return text in (proc / "cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return False


def test_a_run_too_short_to_align_says_why_it_has_no_ate_and_keeps_its_outputs(tmp_path):
    """Two frames cannot be aligned to the ground truth (three non-collinear positions at least):
    the run still ends well with every file, and its summary says why there is no ATE."""
    from helpers import octolog

    out = tmp_path / "two"
    proc = octolog("run", "--source", "synthetic:2", "--out", str(out), "--rerun", "off", "--quiet")
    assert "ATE: none (cannot align trajectories: 2 positions are degenerate" in proc.stdout
    assert (out / "map.bt").exists() and (out / "summary.json").exists()
