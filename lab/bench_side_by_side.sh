#!/usr/bin/env bash
# Lab tool, outside the installed package: is this checkout slower than a baseline? A bench of this
# checkout against a baseline commit, measured side by side: the two run alternately, ROUNDS times each,
# with the same flags, and the medians and their ratio are printed.
#   bash lab/bench_side_by_side.sh BASE_COMMIT ROUNDS -- selfplay <rllock bench selfplay flags>
#   bash lab/bench_side_by_side.sh BASE_COMMIT ROUNDS -- checkers <rllock bench checkers flags>
#   bash lab/bench_side_by_side.sh BASE_COMMIT ROUNDS -- solve <rllock bench solve flags>
# The baseline is checked out in a temporary git worktree and runs with this checkout's .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
base="$1"; rounds="$2"; shift 3
# Without a bench name the flags are bench selfplay's (how the script was first written).
if [[ "$1" == --* ]]; then bench=selfplay; else bench="$1"; shift; fi
tmp="$(mktemp -d)"
trap 'git worktree remove --force "$tmp/base" >/dev/null 2>&1 || true; rm -rf "$tmp"' EXIT
git worktree add --detach "$tmp/base" "$base" >/dev/null 2>&1
head_dir="$(pwd)"
# Each tree's own command line: rllock.orchestration.cli, orchestration.cli before it was installed inside
# rllock, rllock.cli before that.
cli_of() {
  if [ -e "$1/rllock/orchestration" ]; then echo rllock.orchestration.cli
  elif [ -f "$1/orchestration/cli/__main__.py" ]; then echo orchestration.cli
  else echo rllock.cli; fi
}
for i in $(seq "$rounds"); do
  (cd "$tmp/base" && PYTHONPATH="$tmp/base" "$head_dir/.venv/bin/python" -m "$(cli_of "$tmp/base")" \
    bench "$bench" "$@" --json) > "$tmp/base_$i.json"
  (cd "$head_dir" && PYTHONPATH="$head_dir" .venv/bin/python -m "$(cli_of "$head_dir")" \
    bench "$bench" "$@" --json) > "$tmp/head_$i.json"
done
.venv/bin/python - "$tmp" "$rounds" "$base" "$bench" <<'PY'
import json, statistics, sys
tmp, rounds, base, bench = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
docs = {kind: [json.load(open(f"{tmp}/{kind}_{i}.json")) for i in range(1, rounds + 1)] for kind in ("base", "head")}
if bench == "checkers":
    bs = [d["chunks_per_sec"] for d in docs["base"]]
    hs = [d["chunks_per_sec"] for d in docs["head"]]
    print(f"checkers: baseline {base} {statistics.median(bs):,.0f} chunks/s {[round(v) for v in bs]}; "
          f"this checkout {statistics.median(hs):,.0f} {[round(v) for v in hs]}; "
          f"ratio {statistics.median(hs) / statistics.median(bs):.2f}")
    sys.exit()
if bench == "solve":  # seconds to each task's assemblies; the same search finds the same ones in both
    for j, row in enumerate(docs["base"][0]["tasks"]):
        bs = [d["tasks"][j]["seconds"] for d in docs["base"]]
        hs = [d["tasks"][j]["seconds"] for d in docs["head"]]
        found = (docs["base"][0]["tasks"][j]["found"], docs["head"][0]["tasks"][j]["found"])
        print(f"{row['task']}: baseline {base} {statistics.median(bs):.3f} s, this checkout "
              f"{statistics.median(hs):.3f} s, ratio {statistics.median(hs) / statistics.median(bs):.2f}, "
              f"found {found[0]} / {found[1]}")
    total = [sum(t["seconds"] for t in d["tasks"]) for kind in ("base", "head") for d in docs[kind]]
    b_sum, h_sum = statistics.median(total[:rounds]), statistics.median(total[rounds:])
    print(f"all tasks: baseline {b_sum:.2f} s, this checkout {h_sum:.2f} s, ratio {h_sum / b_sum:.2f}")
    sys.exit()
b, h = [d["rows"] for d in docs["base"]], [d["rows"] for d in docs["head"]]
for j, row in enumerate(b[0]):
    bs = [r[j]["simulations_per_sec"] for r in b]
    hs = [r[j]["simulations_per_sec"] for r in h]
    print(f"{row['actors']} actor(s): baseline {base} {statistics.median(bs):.1f} simulations/s {bs}; "
          f"this checkout {statistics.median(hs):.1f} {hs}; ratio {statistics.median(hs) / statistics.median(bs):.2f}")
    print("  this checkout's split (ms per simulation and row):", json.dumps(h[-1][j].get("ms_per_simulation")))
PY
