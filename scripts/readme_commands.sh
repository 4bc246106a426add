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
# Make a puzzle (`rllock serve` runs until Ctrl-C, and the mesh line needs the reader's model.stl: left out)
run $R solve --shape cube4 --pieces 7 --seed 0 --out out/cube4
run $R show out/cube4/assembly_001 --png cube4.png
run $R solve --shape cube5 --pieces 13 --count 5 --time-limit 60 --seed 0 --out out/cube5
run $R verify out/cube5/assembly_001/assembly.json
run $R verify rllock/data/published/Cube_4x4x4_K9.puz --removal path --json
run $R show out/cube4/assembly_001 --png cube.png --gif disassembly.gif --html viewer.html
run $R export out/cube4/assembly_001 --format stl --voxel-size 10 --gap 0.3 --out prints/
run $R export out/cube4/assembly_001 --format xmpuzzle --out burr/
run .venv/bin/python -c '
from pathlib import Path
import rllock

grids = rllock.solve(rllock.make_task("cube5", 13), count=2)
policy = rllock.load_policy("cube4-k9")
result = rllock.generate(policy, count=3, batch=16, time_limit=300, seed=0, out=Path("out/api"))
print(len(grids), result.valid, "valid in", round(result.seconds), "s")'
# Train and research (the cluster walkthrough needs `ray start` and is left out)
run $R pretrained
run $R generate --checkpoint cube4-k9 --count 5 --out out/cube4-k9
run $R bench paper --tasks cube4-k9 --time-limit 60 --out table.md
run $R train --shape cube4 --pieces 8 --minutes 2 --canvas 4 --simulations 64 --logdir runs/cube4-k8
run $R generate --checkpoint runs/cube4-k8 --count 5 --batch 64 --out out/cube4-k8 --time-limit 120
run $R bench learning --checkpoint runs/cube4-k8 --count 5 --time-limit 60
run $R generate --checkpoint general --shape ring --pieces 15 --count 5 --out out/ring-k15 --time-limit 120
run $R train --init general --shape sofa --pieces 19 --minutes 1 --logdir runs/sofa-k19
run $R bench solve --time-limit 20
rm -rf "$log"
