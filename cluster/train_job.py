"""Cluster entry point: `rllock train` joined to the running Ray cluster.

    ray submit cluster/cluster.yaml cluster/train_job.py -- --shape cube6 --pieces 25
    ray job submit --address http://HEAD:8265 --working-dir . -- \
        python cluster/train_job.py --shape cube6 --pieces 25

Arguments are those of `rllock train`; without `--address` it joins the cluster this process runs in
(`auto`: the node's own Ray, as both `ray submit` and Ray Jobs provide). Ray Jobs runs this file in a
temporary copy of the uploaded folder, so there a relative `--logdir` or `--resume` folder (and the
default one) is taken under ~/rllock on the node that runs the job: the run outlives the job.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

# `ray job submit --working-dir .` runs this file from the uploaded repository: make its packages
# importable even where the node has no editable install of it.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rllock.config import TrainConfig  # noqa: E402
from rllock.orchestration.cli.main import entry  # noqa: E402

# Ray Jobs sets this in the environment of the job's entry point.
JOB_ENV = "RAY_JOB_CONFIG_JSON_ENV_VAR"
RUNS_HOME = Path("~/rllock")


def job_args(argv: list[str], *, in_job: bool = False, home: Path = RUNS_HOME) -> list[str]:
    """The `rllock` arguments for `argv`: `train`, the cluster's address unless one is given, and under
    Ray Jobs (`in_job`) relative run folders anchored at `home`."""
    args = list(argv)
    if not any(a == "--address" or a.startswith("--address=") for a in args):
        args += ["--address", "auto"]
    if in_job:
        args = _anchored(args, home.expanduser())
    return ["train", *args]


def _anchored(args: list[str], home: Path) -> list[str]:
    out, given = [], False
    for i, arg in enumerate(args):
        flag, eq, value = arg.partition("=")
        if flag in ("--logdir", "--resume"):
            given = True
            if eq and not Path(value).is_absolute():
                arg = f"{flag}={home / value}"
        elif i > 0 and args[i - 1] in ("--logdir", "--resume") and not Path(arg).is_absolute():
            arg = str(home / arg)
        out.append(arg)
    if not given:
        out += ["--logdir", str(home / TrainConfig().logdir)]
    return out


if __name__ == "__main__":
    sys.exit(entry(job_args(sys.argv[1:], in_job=JOB_ENV in os.environ)))
