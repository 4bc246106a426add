#!/usr/bin/env bash
# Self-play throughput of this checkout against a baseline commit, measured side by side: the two run
# alternately, ROUNDS times each, with the same flags, and the medians and their ratio are printed.
#   bash scripts/bench_side_by_side.sh BASE_COMMIT ROUNDS -- <rllock bench selfplay flags>
# The baseline is checked out in a temporary git worktree and runs with this checkout's .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
base="$1"; rounds="$2"; shift 3
tmp="$(mktemp -d)"
trap 'git worktree remove --force "$tmp/base" >/dev/null 2>&1 || true; rm -rf "$tmp"' EXIT
git worktree add --detach "$tmp/base" "$base" >/dev/null 2>&1
head_dir="$(pwd)"
for i in $(seq "$rounds"); do
  (cd "$tmp/base" && PYTHONPATH="$tmp/base" "$head_dir/.venv/bin/python" -m orchestration.cli bench selfplay "$@" --json) \
    > "$tmp/base_$i.json"
  (cd "$head_dir" && PYTHONPATH="$head_dir" .venv/bin/python -m orchestration.cli bench selfplay "$@" --json) > "$tmp/head_$i.json"
done
.venv/bin/python - "$tmp" "$rounds" "$base" <<'PY'
import json, statistics, sys
tmp, rounds, base = sys.argv[1], int(sys.argv[2]), sys.argv[3]
def rows(kind):
    return [json.load(open(f"{tmp}/{kind}_{i}.json"))["rows"] for i in range(1, rounds + 1)]
b, h = rows("base"), rows("head")
for j, row in enumerate(b[0]):
    bs = [r[j]["simulations_per_sec"] for r in b]
    hs = [r[j]["simulations_per_sec"] for r in h]
    print(f"{row['actors']} actor(s): baseline {base} {statistics.median(bs):.1f} simulations/s {bs}; "
          f"this checkout {statistics.median(hs):.1f} {hs}; ratio {statistics.median(hs) / statistics.median(bs):.2f}")
    print("  this checkout's split (ms per simulation and row):", json.dumps(h[-1][j].get("ms_per_simulation")))
PY
