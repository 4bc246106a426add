"""RL-Lock: interlocking assemblies from voxel shapes.

The public API, for a notebook or a script (names load their modules on first use, so `import rllock`
stays light):

    make_task(shape, pieces, removal="straight")   a task: a shape (built-in name, file or bool grid) and K
    solve(task, count=1, time_limit=60, seed=0)    assemblies by randomized search, no training
    load_policy(checkpoint)                        a trained network and its search settings
    generate(policy, count=, batch=, time_limit=, seed=, out=None)
                                                   the paper's protocol: batched MCTS until `count` valid
    verify(labels, removal="straight")             the full verifier's verdict on a label grid
    read_assembly(path)                            (labels grid, metadata) of an assembly.json or .puz

Layers: the library is `rllock` (core: shapes, topology, reference and fast checkers, env, verifier;
search: network, mcts, solver, inference; files: assembly, checkpoint, export, meshes, render). The
packages `actors` and `learner` build on it, `orchestration` (training loop, Ray actor pool, generation
on Ray) sits above them, and the command line
(`orchestration.cli`) calls it. No module of `rllock` imports the layers above it at
module level.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["generate", "load_policy", "make_task", "read_assembly", "solve", "verify"]

_API = {
    "generate": ("rllock.search.inference", "generate"),
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
