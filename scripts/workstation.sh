#!/usr/bin/env bash
# The GPU workstation's checks in one run, for a machine lent for minutes (figures: docs/results.md; the
# run: docs/notebook/benchmarks.md, "On the GPU workstation"): `bench scaling --preset workstation`, then
# `train-guide` on every core until the deadline, its run folder packed for `--resume` elsewhere. Each step
# has its own time limit, so that one that fails or overruns still leaves the others their time and their
# files.
#
#   scripts/workstation.sh OUT SECONDS [SCALING FLAGS...]
#
# OUT: where the logs, the scaling table and the packed run go; SECONDS: the whole run's budget.
# PYTHON (default python3) must import rllock's dependencies (the repository root is put on PYTHONPATH).
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:?usage: scripts/workstation.sh OUT SECONDS [SCALING FLAGS...]}"
budget="${2:?usage: scripts/workstation.sh OUT SECONDS [SCALING FLAGS...]}"
shift 2
end=$(($(date +%s) + budget))
PY="${PYTHON:-python3}"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
mkdir -p "$out"
left() { echo $((end - $(date +%s))); }

{
  date -u; nproc; free -g | head -2; nvidia-smi -L 2>&1
  git log -1 --format='commit %H' 2>/dev/null
  "$PY" -c 'import sys, jax, flax, optax, numba, numpy, ray, orbax.checkpoint as oc
print(sys.version.split()[0], "jax", jax.__version__, jax.devices(), "flax", flax.__version__, "optax",
      optax.__version__, "orbax", oc.__version__, "numba", numba.__version__, "numpy", numpy.__version__,
      "ray", ray.__version__)'
} >"$out/machine.txt" 2>&1
cat "$out/machine.txt"

# numba's cache once, before any actor would compile it at the same time as the others.
timeout "$(left)" "$PY" -m rllock.core.precompile >"$out/precompile.log" 2>&1
echo "precompile: exit $?, $(left) s left"

# The scaling table first: its figures are the workstation's alone; it may take half of what is left.
timeout $(($(left) / 2)) "$PY" -m rllock.orchestration.cli bench scaling --preset workstation --json "$@" \
  >"$out/scaling.json" 2>"$out/scaling.log"
echo "scaling: exit $?, $(left) s left"

# The guide's training until a minute before the deadline (Ray's start, the last checkpoint and the
# packing fit in it); the flags of the notebook's 2-core runs, on every core.
minutes=$(awk -v s="$(left)" 'BEGIN { printf "%.2f", (s - 50) / 60 }')
timeout $(($(left) - 15)) "$PY" -m rllock.orchestration.cli train-guide --minutes "$minutes" --logdir /tmp/guide-ws \
  --search-seconds 5 --max-voxels 1000 --max-pieces 80 --replay-ratio 100 --batch-size 128 \
  --publish-every 50 --checkpoint-minutes 1 --buffer-capacity 200000 --label reach --max-left 30 \
  >"$out/train-guide.log" 2>&1
echo "train-guide ($minutes min): exit $?, $(left) s left"
tar -C /tmp -czf "$out/guide-ws.tar.gz" guide-ws
ls -la "$out"
