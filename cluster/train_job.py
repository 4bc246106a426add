"""Cluster entry point: `rllock train` joined to the running Ray cluster.

    ray submit cluster/cluster.yaml cluster/train_job.py -- --shape cube6 --pieces 25
    ray job submit --address http://HEAD:8265 --working-dir . -- \
        python cluster/train_job.py --shape cube6 --pieces 25

Arguments are those of `rllock train`; without `--address` it joins the cluster this process runs in
(`auto`: the node's own Ray, as both `ray submit` and Ray Jobs provide).
"""

from __future__ import annotations

import sys
from pathlib import Path

# `ray job submit --working-dir .` runs this file from the uploaded repository: make its packages
# importable even where the node has no editable install of it.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestration.cli.main import main  # noqa: E402


def job_args(argv: list[str]) -> list[str]:
    args = list(argv)
    if not any(a == "--address" or a.startswith("--address=") for a in args):
        args += ["--address", "auto"]
    return ["train", *args]


if __name__ == "__main__":
    sys.exit(main(job_args(sys.argv[1:])))
