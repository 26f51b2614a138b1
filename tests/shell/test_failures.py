"""Failure hygiene (#13): a full disk, a bad --out, an existing session, a run that fails part-way,
files that are not MCAP, and error lines that start on a line of their own. Real processes, real files."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from helpers import octolog
from helpers.recordings import make_tum


def _last_line(err: str) -> str:
    """The last line as a terminal shows it after the fact: split on newlines only (a progress line's
    carriage returns stay in it, so text glued onto it shows)."""
    return [ln for ln in err.split("\n") if ln.strip()][-1]


@pytest.fixture
def small_disk(tmp_path):
    """A 20 MB tmpfs: a disk that fills up a few seconds into a run."""
    disk = tmp_path / "disk"
    disk.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=20m", "tmpfs", str(disk)], capture_output=True,
                          text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs to fill (needs root / CAP_SYS_ADMIN): {proc.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


@pytest.mark.root
@pytest.mark.slow
@pytest.mark.parametrize("rerun", ["save", "off"])
def test_a_full_disk_is_one_line_naming_the_disk_and_the_file(small_disk, rerun):
    out = small_disk / "s"
    proc = octolog("demo", "--out", str(out), "--frames", "150", "--rerun", rerun, check=False, timeout=300)
    assert proc.returncode == 1, proc.stderr
    last = _last_line(proc.stderr)
    assert last.startswith("octolog demo: error: ") and "disk full: " in last, proc.stderr
    assert f"{small_disk}/" in last and f"the disk holding {small_disk}" in last, last
    assert "Traceback" not in proc.stderr, proc.stderr
    assert (out / "INCOMPLETE").is_file() and not (out / "summary.json").exists()


def test_out_that_is_a_file_is_one_line(tmp_path):
    f = tmp_path / "f"
    f.write_text("mine")
    for out, want in ((f, f"--out {f}: is a file, not a folder"),
                      (f / "sub" / "s", f"--out {f / 'sub' / 's'}: cannot make the folder: {f} is a file")):
        proc = octolog("run", "--source", "synthetic:5", "--out", str(out), "--rerun", "off", check=False)
        assert proc.returncode == 1
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"octolog run: error: {want}"), proc.stderr
    assert f.read_text() == "mine"


@pytest.mark.slow
def test_an_existing_session_is_replaced_only_with_overwrite_and_then_whole(tmp_path):
    out = tmp_path / "s"
    octolog("run", "--source", "synthetic:10", "--out", str(out), "--quiet")  # with rerun/*.rrd
    assert not (out / "INCOMPLETE").exists()
    before = (out / "summary.json").read_bytes()
    (out / "logs" / "old.txt").write_text("from the old session")
    for cmd in (["run", "--source", "synthetic:10"], ["demo", "--frames", "10"]):
        proc = octolog(*cmd, "--out", str(out), "--quiet", "--rerun", "off", check=False)
        assert proc.returncode == 1
        assert proc.stderr == f"octolog {cmd[0]}: error: --out {out}: holds a session already; pass --overwrite " \
                              "to replace it\n"
    assert (out / "summary.json").read_bytes() == before
    octolog("demo", "--frames", "10", "--out", str(out), "--quiet", "--rerun", "off", "--overwrite")
    assert not (out / "rerun").exists() and not (out / "logs" / "old.txt").exists()
    files = json.loads((out / "summary.json").read_text())["files"]
    assert sorted(p.name for p in out.iterdir() if p.is_file()) == sorted(files)
    # a folder that is no session is never cleared, --overwrite or not
    other = tmp_path / "home"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    proc = octolog("run", "--source", "synthetic:5", "--out", str(other), "--overwrite", check=False)
    assert proc.returncode == 1 and "not an octolog session" in proc.stderr
    assert (other / "thesis.tex").read_text() == "x"


@pytest.fixture(scope="module")
def failed_run(tmp_path_factory) -> tuple[Path, Path, subprocess.CompletedProcess]:
    """A TUM run whose 21st depth image is truncated: it fails part-way, progress line showing."""
    tmp = tmp_path_factory.mktemp("failed")
    folder = make_tum(tmp / "rgbd_dataset_freiburg1_seq", n=30)  # the name says the camera
    victim = sorted((folder / "depth").iterdir())[20]
    victim.write_bytes(victim.read_bytes()[:40])
    out = tmp / "o"
    proc = octolog("run", "--source", f"tum:{folder}", "--out", str(out), "--rerun", "off", check=False, timeout=300)
    return out, victim, proc


def test_a_failed_run_marks_its_folder_incomplete(failed_run):
    out, victim, proc = failed_run
    assert proc.returncode == 1, proc.stderr
    marker = (out / "INCOMPLETE").read_text()
    assert marker.startswith("octolog run failed: the replay stage exited with code 1") and victim.name in marker
    assert not (out / "summary.json").exists()
    replay = octolog("replay", str(out), "--quiet", "--rerun", "off", check=False)
    assert replay.returncode == 1 and replay.stderr.count("\n") == 1
    assert f"{out}: an incomplete session (INCOMPLETE: octolog run failed" in replay.stderr
    for target in (out, out / "session.mcap"):
        info = octolog("info", str(target)).stdout
        assert f"session {out}: INCOMPLETE (INCOMPLETE: octolog run failed" in info, info


def test_an_error_line_never_shares_the_progress_line(failed_run):
    _, _, proc = failed_run
    assert "10/30 frames" in proc.stderr  # the progress line was there to be glued onto
    errors = [ln for ln in proc.stderr.split("\n") if "error: " in ln]
    assert len(errors) == 2, proc.stderr  # the replay's own line and the session's
    assert all(ln.startswith("octolog ") for ln in errors), proc.stderr
    assert _last_line(proc.stderr).startswith("octolog run: error: the replay stage exited with code 1")


@pytest.mark.parametrize("head", [b"", b"\x89MCAP0\r\n"], ids=["random", "magic-then-random"])
def test_random_bytes_are_no_mcap_for_info_or_recover(tmp_path, head):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(head + bytes(range(256)) * 40)
    out = tmp_path / "recovered.mcap"
    for args in (["info", str(junk)], ["recover", str(junk), str(out)]):
        proc = octolog(*args, check=False)
        assert proc.returncode == 1, proc.stdout
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"octolog {args[0]}: error: {junk}: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mcap"]  # recover wrote nothing, no .part


def test_a_router_that_is_not_there_is_one_line_naming_it_and_no_folder(tmp_path):
    """`run --router EP` with nothing listening at EP: refused before any process starts or any file
    is written, in one line naming EP and what to do, not a minute later blaming the stages."""
    from helpers import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "s"
    proc = octolog("run", "--source", "synthetic:5", "--out", str(out), "--router", endpoint, "--quiet", check=False,
                   timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith(f"octolog run: error: --router {endpoint}: nothing listens at 127.0.0.1:"), proc.stderr
    assert f"octolog router --listen {endpoint}" in proc.stderr
    assert not out.exists()


def test_a_stage_started_alone_says_what_it_waits_for(tmp_path):
    """`octolog replay` with no tracker or mapper on the bus: it says within seconds which stages it
    waits for and that they must run too (read as it comes, then stopped), not a minute of silence."""
    import os
    import sys

    from helpers import ROOT

    proc = subprocess.Popen([sys.executable, "-m", "octolog", "replay", "--source", "synthetic:5", "--no-multicast",
                             "--namespace", f"alone{os.getpid()}", "--rerun", "off", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        said = ""
        for line in proc.stderr:  # blocking reads: the line is the event
            said += line
            if "waiting for the" in line:
                break
    finally:
        proc.kill()
        proc.wait(timeout=60)
    assert "replay: waiting for the tracker stage to appear on the bus" in said, said
    assert "octolog run" in said
