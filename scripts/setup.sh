#!/usr/bin/env bash
# Create ./.venv (if missing) and install ddp into it with the given extras.
#   bash scripts/setup.sh            # core
#   bash scripts/setup.sh dev        # + test tools
# torch==2.13.0 is installed first: a bare `torch` requirement would pull a
# multi-GB CUDA build. Where pip finds a wheel of it without an index (this
# project's machines keep a CPU one in their wheel cache) that one is taken; on a
# machine with an NVIDIA GPU (nvidia-smi) PyPI's CUDA build; elsewhere PyTorch's
# CPU index. TORCH_INDEX_URL names another index, e.g. a CUDA version's:
#   TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128 bash scripts/setup.sh dev
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
if "$VENV/bin/python" -c "import torch, sys; sys.exit(0 if torch.__version__.startswith('2.13.0') else 1)" 2>/dev/null; then
    :  # installed
elif [ -n "${TORCH_INDEX_URL:-}" ]; then
    "${PIP[@]}" install -q --index-url "$TORCH_INDEX_URL" "torch==2.13.0"
elif command -v nvidia-smi >/dev/null 2>&1 \
        || "${PIP[@]}" install -q --dry-run --ignore-installed --no-deps --no-index "torch==2.13.0" >/dev/null 2>&1; then
    "${PIP[@]}" install -q "torch==2.13.0"  # a GPU: PyPI's CUDA build; or the wheel pip finds locally
else
    "${PIP[@]}" install -q --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0"  # no GPU: the CPU build
fi
if [ -n "$EXTRAS" ]; then
    "${PIP[@]}" install -q -e ".[$EXTRAS]"
else
    "${PIP[@]}" install -q -e .
fi
echo "ddp installed in $VENV ($("$VENV/bin/python" -c 'import torch; print("torch", torch.__version__)'))"
