#!/usr/bin/env bash
# Install ddp with its test extras into ./.venv (and the franky-sim Franka simulator into
# ./.venv-franky-sim, for the real-robot backend's tests) and run the test suite.
#   bash scripts/test.sh           # default suite (slow tests excluded)
#   bash scripts/test.sh --slow    # only the slow tests
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh dev,sim,video
bash scripts/setup_franky_sim.sh
VENV="${DDP_VENV:-.venv}"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
args=() slow=0
for a in "$@"; do  # --slow anywhere among the arguments
    if [ "$a" = "--slow" ]; then slow=1; else args+=("$a"); fi
done
if [ "$slow" = 1 ]; then
    exec "$VENV/bin/python" -m pytest -m slow ${args[@]+"${args[@]}"}
fi
exec "$VENV/bin/python" -m pytest ${args[@]+"${args[@]}"}
