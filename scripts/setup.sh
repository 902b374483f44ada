#!/usr/bin/env bash
# Create ./.venv (if missing) and install ddp into it with the given extras.
#   bash scripts/setup.sh            # core
#   bash scripts/setup.sh dev        # + test tools
# torch==2.13.0 is installed first: a bare `torch` requirement would pull a
# multi-GB CUDA build. Where pip finds a CPU wheel of it (this project's machines
# keep one in their wheel cache) that one is taken; elsewhere on Linux, PyPI's
# torch==2.13.0 is the CUDA build: name PyTorch's CPU index instead,
#   TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu bash scripts/setup.sh dev
set -euo pipefail
cd "$(dirname "$0")/.."
EXTRAS="${1:-}"
VENV="${DDP_VENV:-.venv}"
PY="${PYTHON:-python3}"
if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip)  # an array: a venv path with a space stays one word
"${PIP[@]}" install -q --upgrade pip >/dev/null
"$VENV/bin/python" -c "import torch, sys; sys.exit(0 if torch.__version__.startswith('2.13.0') else 1)" 2>/dev/null \
    || "${PIP[@]}" install -q ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} "torch==2.13.0"
if [ -n "$EXTRAS" ]; then
    "${PIP[@]}" install -q -e ".[$EXTRAS]"
else
    "${PIP[@]}" install -q -e .
fi
echo "ddp installed in $VENV ($("$VENV/bin/python" -c 'import torch; print("torch", torch.__version__)'))"
