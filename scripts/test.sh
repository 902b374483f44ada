#!/usr/bin/env bash
# Install ddp with its test extras into ./.venv and run the test suite.
#   bash scripts/test.sh           # default suite (slow tests excluded)
#   bash scripts/test.sh --slow    # only the slow tests
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh dev,metaworld
VENV="${DDP_VENV:-.venv}"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
if [ "${1:-}" = "--slow" ]; then
    shift
    exec "$VENV/bin/python" -m pytest -m slow "$@"
fi
exec "$VENV/bin/python" -m pytest "$@"
