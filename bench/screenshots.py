"""Screenshots of the Rerun viewer on a session, as a user sees it: docs/img/*.png.

Runs `octolog demo`, `octolog run` on TUM fr1/xyz first300 and on the synthetic room with two people
walking through it (`people=cross`: the map without them, what was kept out in red at `map/movers`;
Rerun on, the defaults), opens each
session's recordings in the real viewer on a virtual display (Xvfb, Mesa's software Vulkan) and
captures the screen once the viewer has caught up with the end of the data.

    make screenshots        # installs xvfb, mesa-vulkan-drivers, imagemagick, xdotool (apt) first
    python bench/screenshots.py [--out docs/img] [--tum PATH] [--wait 60] [--shots demo,tum,people]

The viewer opens the recordings with the blueprint they carry (octolog.kit.viz); the script presses
the time panel's "follow latest data" button so that each shot shows the whole map.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
DISPLAY = ":93"
LOAD_S = 20.0
FOLLOW_BUTTON = ("54", "985")  # in the viewer's time panel (rerun-sdk 0.41, 1600x1000)
IDLE_POINTER = ("1100", "18")  # an empty spot of its top bar
SIZE = "1600x1000"
PEOPLE = "synthetic:600:noise=d455:imu=200:people=cross"  # bench/people.py's first scene


def _need(tool: str) -> str:
    path = shutil.which(tool)
    if path is None:
        sys.exit(f"screenshots: {tool} not found (make screenshots installs it)")
    return path


def _session(args: list[str], out: Path) -> Path:
    subprocess.run([sys.executable, "-m", "octolog", *args, "--out", str(out), "--quiet", "--overwrite"],
                   check=True, cwd=ROOT)
    return out


def _shot(session: Path, png: Path, wait_s: float) -> None:
    """Open the session's recordings in the viewer on the virtual display and capture it."""
    env = {**os.environ, "DISPLAY": DISPLAY, "RERUN_DISABLE_ANALYTICS": "1"}
    rerun = str(Path(sys.executable).parent / "rerun")
    viewer = subprocess.Popen([rerun, *map(str, sorted((session / "rerun").glob("*.rrd")))], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(LOAD_S)  # the viewer reads the recordings and starts playing them
        # the time panel's "follow latest data" button (bottom left of a 1600x1000 window): the whole
        # map at once, where playing it in real time on a software rasteriser takes minutes
        xdotool = _need("xdotool")
        subprocess.run([xdotool, "mousemove", *FOLLOW_BUTTON, "click", "1"], env=env, check=True)
        subprocess.run([xdotool, "mousemove", *IDLE_POINTER], env=env, check=True)  # no hover tooltip
        time.sleep(wait_s)  # software rendering: the viewer needs this long to draw the whole map
        png.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([_need("import"), "-window", "root", str(png)], env=env, check=True)
    finally:
        viewer.terminate()
        viewer.wait(timeout=30)
    print(f"screenshots: {png}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(ROOT / "docs" / "img"), help="folder for the PNGs (default docs/img)")
    p.add_argument("--tum", default=os.path.join(os.environ.get("OCTOLOG_DATA", str(ROOT.parent / "shared" / "data")),
                                                 "tum", "rgbd_dataset_freiburg1_xyz_first300"),
                   help="TUM folder for the second shot (default: the shared first300)")
    p.add_argument("--wait", type=float, default=60.0, help="seconds the viewer gets before each capture")
    p.add_argument("--shots", default="demo,tum,people", help="which shots (default all three)")
    args = p.parse_args()
    # a compositing X server captures black: Xvfb without the Composite extension
    xvfb = subprocess.Popen([_need("Xvfb"), DISPLAY, "-screen", "0", f"{SIZE}x24", "-extension", "Composite"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            shots = args.shots.split(",")
            if "demo" in shots:
                demo = _session(["demo"], Path(tmp) / "demo")
                _shot(demo, Path(args.out) / "viewer-demo.png", args.wait)
            if "tum" in shots and Path(args.tum).is_dir():
                tum = _session(["run", "--source", f"tum:{args.tum}"], Path(tmp) / "tum")
                _shot(tum, Path(args.out) / "viewer-tum-first300.png", args.wait)
            elif "tum" in shots:
                print(f"screenshots: {args.tum} not found, no TUM shot")
            if "people" in shots:
                people = _session(["run", "--source", PEOPLE], Path(tmp) / "people")
                _shot(people, Path(args.out) / "viewer-people.png", args.wait)
    finally:
        xvfb.terminate()
        xvfb.wait(timeout=30)


if __name__ == "__main__":
    main()
