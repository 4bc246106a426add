#!/usr/bin/env bash
# Trains the multi-task network (one network for many shapes and piece counts) into runs/general/ (or
# --resume it), then ships its best checkpoint into the package as `general`.
#   bash scripts/train_general.sh [MINUTES] [--resume]
# The held-out shapes of `rllock bench transfer` (sofa, cubeweird, ring, stairs, tube) are not in the
# task list: only cubes, one box and random shapes are.
set -euo pipefail
cd "$(dirname "$0")/.."
minutes="${1:-60}"; resume="${2:-}"
logdir="runs/general"
if [ "$resume" = "--resume" ]; then
  .venv/bin/rllock train --resume "$logdir" --minutes "$minutes"
else
  # As the per-task checkpoints (scripts/train_paper.sh): self-imitation, Adam at 3e-4 and replay ratio 8;
  # but 16 simulations: on 2 cores the 6^3 and 200-voxel tasks would leave 64-simulation self-play with
  # too few episodes per task group in an hour, and cube4-k7 learned as well at 16 as at 256
  # (docs/notebook/benchmarks.md). Validation: 16 episodes of one fixed task per group every 10 minutes.
  .venv/bin/rllock train --tasks "cube4:6-9,cube5:12-16,cube6:18-25,box:6x5x4:8-12,random:60-200:6-20" \
    --minutes "$minutes" --logdir "$logdir" --simulations 16 --actors 2 --learning-rate 3e-4 \
    --replay-ratio 8 --success-fraction 0.25 --validate-minutes 10 --validation-episodes 16 \
    --checkpoint-minutes 5
fi
.venv/bin/rllock pretrained --ship "$logdir" --name general
