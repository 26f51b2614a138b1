"""Rerun output (kit/viz.py): a viewer that is not there never costs a run or its recording."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
from helpers import free_port, octolog, rerun_cli

from octolog.kit import viz


def test_a_run_streaming_to_no_viewer_completes_and_saves_its_recordings(tmp_path):
    """`octolog run --rerun connect:URL` with nothing listening at URL: the run ends as usual, each
    stage's recording is in OUT/rerun, and the summary (printed and summary.json) says the viewer
    was not reachable."""
    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    out = tmp_path / "s"
    proc = octolog("run", "--source", "synthetic:5", "--out", str(out), "--quiet", "--rerun", f"connect:{url}")
    assert sorted(p.name for p in (out / "rerun").glob("*.rrd")) == ["mapper.rrd", "replay.rrd", "tracker.rrd"]
    missed = json.loads((out / "summary.json").read_text())["viewer_missed"]
    assert missed["url"] == url and missed["saved"] == str(out / "rerun"), missed
    assert f"viewer: not reachable at {url}" in proc.stdout, proc.stdout
    assert f"no Rerun viewer at {url}" in proc.stderr, proc.stderr


def test_a_viewer_gone_part_way_leaves_the_saved_copy_whole(tmp_path, monkeypatch):
    """A stage streaming to a viewer with `$OCTOLOG_RERUN_COPY` set (as `octolog run` sets it) writes
    the same recording to a file; when the viewer cannot be reached at the end, closing warns, notes
    it for the stage's report and raises nothing, and the file holds every row."""
    monkeypatch.setenv(viz.COPY_ENV, str(tmp_path))
    monkeypatch.setattr(viz, "VIEWER_FLUSH_S", 1.0)
    monkeypatch.setattr(viz, "VIEWER_MISSED", {})
    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    with viz.Viz(f"connect:{url}", "tracker", "test") as v:
        for i in range(20):
            v.set_time(1_000_000_000 + i * 33_333_333, i)
            v.rec.log("world/points", v._rr.Points3D(np.full((4, 3), float(i), np.float32)))
    assert viz.VIEWER_MISSED["url"] == url and viz.VIEWER_MISSED["saved"] == str(tmp_path / "tracker.rrd")
    printed = subprocess.run([rerun_cli(), "rrd", "print", str(tmp_path / "tracker.rrd")], capture_output=True,
                             text=True, timeout=300, check=True, env={**os.environ, "RERUN_DISABLE_ANALYTICS": "1"})
    rows = [int(m) for m in re.findall(r"with (\d+) rows .* - /world/points ", printed.stdout)]
    assert sum(rows) == 20, printed.stdout


def test_a_viewer_address_is_probed_before_anything_streams():
    """What `octolog run` checks before it starts the stages: a port nothing listens at, a URL
    without a host."""
    assert "nothing listens at 127.0.0.1:" in viz.viewer_unreachable(f"rerun+http://127.0.0.1:{free_port()}/proxy")
    assert viz.viewer_unreachable("rerun+http:///proxy") == "rerun+http:///proxy names no host"


def test_a_stage_that_logs_to_rerun_does_not_load_pandas(tmp_path):
    """pyarrow's first conversion would import pandas (0.15 s of CPU per stage, for no use): a Viz
    keeps it out, and pandas still imports afterwards for whoever needs it (evo)."""
    code = ("import sys, numpy as np\n"
            "from octolog.kit.viz import Viz\n"
            f"v = Viz('save:{tmp_path}', 'tracker', 'x')\n"
            "v.scalar('tracker/ms', 1.0)\n"
            "v.close()\n"
            "assert 'pandas' not in sys.modules, 'pandas was loaded'\n"
            "import pandas, pyarrow\n"
            "assert pyarrow.array(pandas.Series([1, 2])).to_pylist() == [1, 2]\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    assert (tmp_path / "tracker.rrd").stat().st_size > 0
