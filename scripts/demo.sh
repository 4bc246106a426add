#!/usr/bin/env bash
# The main job: installs what it needs, trains RL-Lock for 2 minutes on a 6-piece 4x4x4 cube (local Ray,
# self-play actors, JAX learner), generates an assembly from the trained checkpoint, verifies it, and
# leaves it with its picture under out/demo/. It ends with one next step: the TensorBoard command.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
rm -rf out/demo-run out/demo
.venv/bin/rllock train --shape cube4 --pieces 6 --minutes 2 --canvas 4 --simulations 32 \
  --validate-minutes 1 --validation-episodes 16 --learning-rate 3e-4 --logdir out/demo-run
.venv/bin/rllock generate --checkpoint out/demo-run --count 1 --batch 16 --time-limit 300 --out out/demo
.venv/bin/rllock verify out/demo/assembly_001/assembly.json
echo "assembly: out/demo/assembly_001/assembly.json (.puz beside it); picture: out/demo/assembly_001/assembly.png"
echo "next: watch the training curves with .venv/bin/tensorboard --logdir out/demo-run (then open http://localhost:6006)"
