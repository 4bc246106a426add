"""RL-Lock: interlocking assemblies from voxel shapes.

The public API, for a notebook or a script (names load their modules on first use, so `import rllock`
stays light):

    make_task(shape, pieces, removal="straight")   a task: a shape (built-in name, file or bool grid) and K
    solve(task, count=1, time_limit=60, seed=0, guide=None, threads=1)
                                                   assemblies by randomized search, no training; with a
                                                   guide network (`load_guide`) picking its restarts;
                                                   on `threads` cores, the same search sooner
    load_guide(checkpoint="guide")                 a guide network: the shipped one, or a train-guide run
    load_policy(checkpoint)                        a trained network and its search settings
    generate(policy, count=, batch=, time_limit=, seed=, out=None)
                                                   the paper's protocol: batched MCTS until `count` valid
    verify(labels, removal="straight")             the full verifier's verdict on a label grid
    read_assembly(path)                            (labels grid, metadata) of an assembly.json or .puz

Layers, each importing only from itself and the ones before it (tests/test_structure.py checks every
import): `rllock.errors`, `rllock.config` and `rllock.process` at the base; `rllock.core` (shapes,
topology, the reference and the compiled checkers, the environment, the verifier, task sets);
`rllock.files` (assembly files, checkpoints, export, pictures); `rllock.search` (the network, MCTS, the
solver, inference, shipped checkpoints). The packages `actors` and `learner` build on the library,
`orchestration` (the training loop, the Ray actor pool, generation on Ray) sits above them, and the
command line (`rllock.orchestration.cli`) and the benches (`rllock.orchestration.bench`) above everything.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["generate", "load_guide", "load_policy", "make_task", "read_assembly", "solve", "verify"]

_API = {
    "generate": ("rllock.search.inference", "generate"),
    "load_guide": ("rllock.search.guide_checkpoint", "load_guide"),
    "load_policy": ("rllock.search.inference", "load_policy"),
    "make_task": ("rllock.core.env", "make_task"),
    "read_assembly": ("rllock.files.assembly", "read_assembly"),
    "solve": ("rllock.search.solver", "solve"),
    "verify": ("rllock.core.verifier", "verify_labels"),
}


def __getattr__(name: str) -> Any:
    if name not in _API:
        raise AttributeError(f"module 'rllock' has no attribute {name!r}")
    module, attr = _API[name]
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
