"""Lab study, outside the installed package.
Question: How long does a fresh process take to its first generated assembly?
Answer: docs/results.md; the measurements: docs/notebook/benchmarks.md,
"First contact".

Start-up: `rllock generate --checkpoint cube4-k7 --count 5` in two source trees, side by side
(alternating rounds), JAX's persistent cache off; the wall time of each process and the seconds per valid
assembly it prints, their medians and the ratio.

    python lab/bench_startup.py BASELINE_TREE THIS_TREE ROUNDS   (e.g. a `git worktree` of the baseline)
"""

import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

base, head, rounds = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
py = str(head / ".venv/bin/python")


def run(tree: Path) -> tuple[float, float]:
    out = Path(tempfile.mkdtemp()) / "out"
    t = time.perf_counter()
    p = subprocess.run(
        [
            py,
            "-m",
            "rllock.orchestration.cli",
            "generate",
            "--checkpoint",
            "cube4-k7",
            "--count",
            "5",
            "--out",
            str(out),
        ],
        cwd=tree,
        env={**os.environ, "PYTHONPATH": str(tree), "RLLOCK_JAX_CACHE": "off"},
        capture_output=True,
        text=True,
        check=True,
    )
    return time.perf_counter() - t, float(re.search(r"([0-9.]+) s per valid", p.stdout).group(1))


rows = {"base": [], "head": []}
for i in range(rounds):
    for arm, tree in (("base", base), ("head", head)):
        rows[arm].append(run(tree))
        wall, per_valid = rows[arm][-1]
        print(f"round {i + 1} {arm}: {wall:.1f} s wall, {per_valid:.2f} s per valid", flush=True)
med = {a: [statistics.median(r[k] for r in rs) for k in range(2)] for a, rs in rows.items()}
for a, m in med.items():
    print(f"median {a}: {m[0]:.1f} s wall, {m[1]:.2f} s per valid")
ratio = [h / b for h, b in zip(med["head"], med["base"])]
print(f"head / base: wall {ratio[0]:.2f}, per valid {ratio[1]:.2f}")
