#!/usr/bin/env bash
# Set up the real-robot backend's test bench: the franky-sim Franka simulator in its OWN
# virtualenv, and the franky client in the main one.
#   bash scripts/setup_franky_sim.sh
# franky-sim (a libfranka-protocol server backed by MuJoCo) pulls numpy 2 and MuJoCo 4, which
# robosuite's and MetaWorld's pins exclude from ./.venv; it runs as a separate process
# (ddp/envs/franka/franky_sim_server.py), so it gets its own environment:
#   FRANKY_SIM_VENV  (default ./.venv-franky-sim)   franky-sim 1.0.4 + MuJoCo 4.0.0 (~660 MB)
#   DDP_VENV         (default ./.venv)              + the `real` extra's clients: franky-control 2.0.0
#                                                    (works with numpy 1.26) and pyrealsense2
# pyrealsense2 needs the libusb-1.0-0 system library: installed with apt-get when run as root.
# Idempotent: a second run checks the versions and installs nothing.
set -euo pipefail
cd "$(dirname "$0")/.."
FS_VENV="${FRANKY_SIM_VENV:-.venv-franky-sim}"
VENV="${DDP_VENV:-.venv}"
PY="${PYTHON:-python3}"
FRANKY_SIM="franky-sim==1.0.4"
MUJOCO="mujoco==4.0.0"
FRANKY="franky-control==2.0.0"
REALSENSE="pyrealsense2>=2.55"

if [ ! -x "$FS_VENV/bin/python" ]; then
    "$PY" -m venv "$FS_VENV"
fi
if ! "$FS_VENV/bin/python" - <<'EOF' 2>/dev/null
import importlib.metadata as m, sys
sys.exit(0 if (m.version("franky-sim"), m.version("mujoco")) == ("1.0.4", "4.0.0") else 1)
EOF
then
    "$FS_VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
    "$FS_VENV/bin/python" -m pip install -q "$FRANKY_SIM" "$MUJOCO"
fi
"$FS_VENV/bin/python" -c "import franky_sim, mujoco, numpy; print('franky-sim server env:', '$FS_VENV', '(mujoco', mujoco.__version__ + ', numpy', numpy.__version__ + ')')"

if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then  # (grep -q can SIGPIPE ldconfig under pipefail)
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 \
            || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1; } \
            || echo "note: could not install libusb-1.0-0; pyrealsense2 will not import" >&2
    else
        echo "note: pyrealsense2 needs libusb-1.0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0)" >&2
    fi
fi

if [ -x "$VENV/bin/python" ]; then
    if ! "$VENV/bin/python" -c "import importlib.metadata as m, sys; m.version('pyrealsense2'); sys.exit(0 if m.version('franky-control') == '2.0.0' else 1)" 2>/dev/null; then
        "$VENV/bin/python" -m pip install -q "$FRANKY" "$REALSENSE"
    fi
    "$VENV/bin/python" -c "import franky; print('franky client in', '$VENV')"
else
    echo "note: $VENV does not exist; install the clients with: pip install 'ddp[real]'" >&2
fi
