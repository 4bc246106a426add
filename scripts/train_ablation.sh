#!/usr/bin/env bash
# The ablation's training runs: each method on each task with the same budget, into
# runs/ablation/<method>/<task>/, for `rllock bench ablation`.
#   bash scripts/train_ablation.sh MINUTES [TASKS]     (TASKS default: cube4-k7 cube4-k8 cube4-k9 cube5-k13)
# Every method gets the same flags apart from --method; each method's own search and buffer settings
# apply (rllock/search/methods.py). Validation: 16 episodes every 5 minutes (RL-Lock_Action's episodes take
# n(K-1) searches each, so 64 would eat much of a short budget).
set -euo pipefail
cd "$(dirname "$0")/.."
minutes="$1"; shift
tasks="${*:-cube4-k7 cube4-k8 cube4-k9 cube5-k13}"
for task in $tasks; do
  shape="${task%%-*}"; pieces="${task##*-k}"
  for method in rl-lock rl-lock-action ppo; do
    .venv/bin/rllock train --method "$method" --shape "$shape" --pieces "$pieces" --minutes "$minutes" \
      --logdir "runs/ablation/$method/$task" --actors 2 --learning-rate 3e-4 --validate-minutes 5 \
      --validation-episodes 16 --checkpoint-minutes 5
  done
done
