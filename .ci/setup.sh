#!/usr/bin/env bash
# Sets up a fresh machine: system libraries, a virtual environment, pinned dependencies, octolog.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}

# open3d and pyrealsense2 need libusb at import time; libgomp for open3d's OpenMP; pyorbslam3's
# _core.so links the OpenGL/X11 runtime (ldd: libOpenGL, libGLX/libGL, libEGL, libSM, libICE, libX11, libXext).
need=()
for pkg in libusb-1.0-0 libgomp1 libgl1 libegl1 libopengl0 libsm6 libice6 libx11-6 libxext6; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ]; then
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
    else
        sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null
    fi
fi

[ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -r requirements.lock
"$VENV/bin/python" -m pip install -q --no-deps -e .
touch "$VENV/.installed"
