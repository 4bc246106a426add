#!/usr/bin/env bash
# The README's commands in order, run from the repository root of a fresh clone after `bash scripts/demo.sh`
# (which installs .venv). Budgets are capped where the README's would run for up to an hour (train
# --minutes, --time-limit, --episodes, bench subsets); each command's last lines, any warning or error
# line on stderr, its exit status and its seconds are printed.
set -uo pipefail
cd "$(dirname "$0")/.."
R=.venv/bin/rllock
log="$(mktemp -d)"
run() {
  local s; s=$(date +%s)
  echo "### $*"
  "$@" > "$log/out" 2> "$log/err"
  local c=$?
  tail -4 "$log/out"
  grep -E "Traceback|WARNING|Warning|error" "$log/err" | head -3
  echo "-> exit $c in $(( $(date +%s) - s )) s"
}
run $R pretrained
run $R generate --checkpoint cube4-k9 --count 5 --out out/cube4-k9
run $R bench learning --checkpoint cube4-k9 --count 5 --time-limit 120
run $R bench paper --tasks cube4-k9 --time-limit 60 --out table.md
run $R train --shape cube4 --pieces 8 --minutes 2 --canvas 4 --simulations 64 --logdir runs/cube4-k8
run $R generate --checkpoint runs/cube4-k8 --count 5 --batch 64 --out out/cube4-k8 --time-limit 120
run $R bench learning --checkpoint runs/cube4-k8 --count 5 --time-limit 60
run $R bench success --checkpoint cube4-k8 --checkpoint runs/cube4-k8 --episodes 64
run $R generate --checkpoint runs/cube4-k8 --count 5 --actors 2 --out out/cube4-k8-ray --time-limit 120
run $R bench selfplay --actors 1,2 --seconds 15
run $R generate --checkpoint general --shape ring --pieces 15 --count 5 --out out/ring-k15 --time-limit 120
run $R bench learning --checkpoint general --shape stairs --pieces 16 --time-limit 60
run $R bench transfer --checkpoint general --tasks sofa:12,cube4:9 --time-limit 30 --count 1
run $R train --init general --shape sofa --pieces 19 --minutes 1 --logdir runs/sofa-k19
run .venv/bin/python -c '
from pathlib import Path
import rllock

policy = rllock.load_policy("cube4-k9")
result = rllock.generate(policy, count=3, batch=16, time_limit=300, seed=0, out=Path("out/api"))
print(result.valid, "valid in", round(result.seconds), "s")
print(len(rllock.solve(rllock.make_task("cube5", 13), count=2)))'
run $R solve --shape cube5 --pieces 13 --count 5 --time-limit 60 --seed 0 --out out/cube5
run $R bench checkers
run $R bench solve --tasks 5^3:13,6^3:20
rm -rf "$log"
