#!/usr/bin/env bash
# Install ddp and run the quickstart: a short real DDP training run on
# synthetic point-cloud demonstrations (about 2 minutes on a 2-core CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
VENV="${DDP_VENV:-.venv}"
"$VENV/bin/ddp" summary recipes/quickstart.yaml
exec "$VENV/bin/ddp" train recipes/quickstart.yaml --no-resume "$@"
