#!/usr/bin/env bash
# Install ddp (with MetaWorld) and run the quickstart: scripted-expert demos on
# MetaWorld drawer-open, train DDP and the DP3 baseline (CPU-sized), evaluate
# both in distribution and under the paper's OOD displacement, print the table.
# About 9-10 minutes on a 2-core CPU. Extra arguments go to `ddp run`
# (e.g. --episodes 10, --set train.max_steps=400).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh metaworld
VENV="${DDP_VENV:-.venv}"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
"$VENV/bin/ddp" demos recipes/metaworld/quickstart_ddp.yaml
# ten environments stepped as one batch: one policy call per chunk for all of them (evaluation 2x faster);
# the world model's loss on half of each batch, its future targets from a table re-encoded every 100 steps
# (issue #12's opt-in training paths: DDP trains in 340 s instead of 432, the same table; README)
exec "$VENV/bin/ddp" run recipes/metaworld/quickstart_ddp.yaml recipes/metaworld/quickstart_dp3.yaml --no-resume \
    --set eval.num_envs=10 --set world_model.batch_fraction=0.5 --set world_model.target_refresh_every=100 "$@"
