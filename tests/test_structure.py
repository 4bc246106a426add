"""The project's structure: layers, the public API, and flags generated from the one config."""

from __future__ import annotations

import argparse
import ast
import os
import subprocess
import sys
from pathlib import Path

from rllock.config import MCTSConfig, NetConfig, SelfPlayConfig, TrainConfig, from_flat, from_json, to_json
from rllock.orchestration.cli.flags import add_flags, field_docs, from_flags

ROOT = Path(__file__).resolve().parents[1]
# The floors of the house, lowest first. A module may import its own floor and any floor below, but
# not a part that is INDEPENDENT of its own. The longest prefix decides a module's part.
# `rllock/__init__.py` names its API's modules as strings and imports none of them.
FLOORS: list[tuple[str, ...]] = [
    ("rllock.errors", "rllock.config", "rllock.process"),
    ("rllock.core",),
    ("rllock.files",),
    ("rllock.search",),
    ("rllock.actors", "rllock.learner"),
    ("rllock.orchestration",),
    ("rllock.orchestration.service",),
    ("rllock.orchestration.cli",),
    ("rllock.orchestration.bench",),
    ("rllock.orchestration.cli.main", "rllock.orchestration.cli.__main__"),
    ("cluster",),
]
INDEPENDENT = {frozenset({"rllock.actors", "rllock.learner"})}
PARTS = {prefix: floor for floor, prefixes in enumerate(FLOORS) for prefix in prefixes}
# The repository's top-level folders and the names they are imported as: actors/, learner/ and
# orchestration/ are installed inside the one `rllock` package (rllock/actors is a link to ../actors), so
# that `pip install` adds no generic top-level name to a user's environment; cluster/ is the job entry
# point of the repository, not installed.
HOMES = {
    "rllock": "rllock",
    "actors": "rllock.actors",
    "learner": "rllock.learner",
    "orchestration": "rllock.orchestration",
    "cluster": "cluster",
}
PACKAGES = tuple(HOMES)  # folders
TOP_NAMES = ("rllock", "cluster")  # what the project's modules are imported as


def _module_name(path: Path) -> str:
    folder, *rest = path.relative_to(ROOT).with_suffix("").parts
    parts = [*HOMES[folder].split("."), *rest]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _sources(folder: str) -> list[Path]:
    """The .py files of a top-level folder, not through links (rllock/actors is actors/ again)."""
    found = []
    for here, _dirs, files in os.walk(ROOT / folder):  # os.walk does not follow links
        found += [Path(here) / f for f in files if f.endswith(".py")]
    return sorted(found)


def _part(module: str) -> str | None:
    """The longest prefix in FLOORS that `module` falls under."""
    found = [p for p in PARTS if module == p or module.startswith(p + ".")]
    return max(found, key=len) if found else None


def _import_statements(path: Path, name: str) -> list[tuple[str, list[str]]]:
    """Every import of the module `name` (at `path`), at module level or inside functions: (the module it
    names, relative ones resolved; the names it takes from it, none for `import m`)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            found.append((base, [a.name for a in node.names]))
    return found


def _imports(path: Path) -> set[str]:
    """Every project module `path` imports, at module level or inside functions, relative ones resolved."""
    found = {base for base, _ in _import_statements(path, _module_name(path))}
    return {m for m in found if m.split(".")[0] in TOP_NAMES}


def _layer_violations() -> dict[str, list[str]]:
    bad: dict[str, list[str]] = {}
    for package in PACKAGES:
        for path in _sources(package):
            here = _part(_module_name(path))
            if here is None:  # rllock/__init__.py, the facade
                continue
            for target in sorted(_imports(path)):
                there = _part(target)
                if there is None:
                    bad.setdefault(str(path.relative_to(ROOT)), []).append(target)
                elif PARTS[there] > PARTS[here] or frozenset({here, there}) in INDEPENDENT:
                    bad.setdefault(str(path.relative_to(ROOT)), []).append(target)
    return bad


def test_every_import_goes_down_the_floors():
    assert _layer_violations() == {}


def test_the_layer_check_sees_imports_inside_functions(tmp_path):
    source = "def f():\n    from rllock.orchestration.train import train\n    from . import env\n"
    path = ROOT / "rllock" / "core" / "_probe_not_a_module.py"
    try:
        path.write_text(source)
        assert _imports(path) == {"rllock.orchestration.train", "rllock.core"}
        assert _layer_violations() == {"rllock/core/_probe_not_a_module.py": ["rllock.orchestration.train"]}
    finally:
        path.unlink()


def _runs(path: Path, name: str, modules: set[str]) -> set[str]:
    """The project modules (of `modules`) whose code importing module `name` (at `path`) may run, at module
    level or inside functions: each module an import names, and the packages above it (their __init__
    runs first). A package's __init__ importing its own submodules does not import itself."""
    named = [
        m
        for base, names in _import_statements(path, name)
        for m in (base, *(f"{base}.{n}" for n in names))  # a name may be a submodule
    ]
    found = {".".join(m.split(".")[:i]) for m in named for i in range(1, m.count(".") + 2)} & modules
    return found - {name} if path.name == "__init__.py" else found


def _import_graph(probes: dict[str, Path] | None = None) -> dict[str, set[str]]:
    """Every project module and the modules it imports (`_runs`); `probes`: more modules, by name."""
    files = {_module_name(p): p for package in PACKAGES for p in _sources(package)}
    files |= probes or {}
    return {name: _runs(path, name, set(files)) for name, path in files.items()}


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of `graph`: its strongly connected components of more than one module (Tarjan),
    and the modules that import themselves."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = stack[stack.index(v) :]
            del stack[stack.index(v) :]
            if len(component) > 1 or v in graph[v]:
                circles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(circles)


def test_no_import_circle_among_the_project_modules():
    """A circle (even one broken by an import inside a function) means two modules that are one."""
    assert _circles(_import_graph()) == []


def test_the_circle_check_sees_imports_inside_functions_and_package_inits(tmp_path):
    """Probe modules, named as if they were in the tree but kept out of it (a probe in the tree would be
    a circle to every other run of the check meanwhile)."""
    sources = {
        # a circle closed by an import inside a function
        "rllock.orchestration._probe_a": ("a.py", "from rllock.orchestration import _probe_b\n"),
        "rllock.orchestration._probe_b": ("b.py", "def f():\n    from ._probe_a import f\n"),
        # a module that imports itself through its package
        "rllock.orchestration._probe_self": (
            "self.py",
            "def f():\n    from rllock.orchestration import _probe_self\n",
        ),
        # a circle through a package's __init__
        "rllock.orchestration._probe_pkg": (
            "pkg/__init__.py",
            "from rllock.orchestration._probe_pkg.inner import g\n",
        ),
        "rllock.orchestration._probe_pkg.inner": (
            "pkg/inner.py",
            "from rllock.orchestration._probe_pkg import h\n",
        ),
        # no circle: an __init__ importing its own submodule, which imports nothing of the package
        "rllock.orchestration._probe_ok": ("ok/__init__.py", "from . import inner\n"),
        "rllock.orchestration._probe_ok.inner": ("ok/inner.py", "import rllock.orchestration.pool\n"),
    }
    probes = {}
    for name, (file, source) in sources.items():
        probes[name] = tmp_path / file
        probes[name].parent.mkdir(exist_ok=True)
        probes[name].write_text(source)
    assert _circles(_import_graph(probes)) == [
        ["rllock.orchestration._probe_a", "rllock.orchestration._probe_b"],
        ["rllock.orchestration._probe_pkg", "rllock.orchestration._probe_pkg.inner"],
        ["rllock.orchestration._probe_self"],
    ]


def test_every_folder_says_what_its_layer_is():
    for package in PACKAGES:
        for init in (p for p in _sources(package) if p.name == "__init__.py"):
            doc = ast.get_docstring(ast.parse(init.read_text()))
            assert doc and len(doc) > 40, init


def test_the_public_api_is_light_and_complete():
    code = (
        "import sys, rllock; assert 'jax' not in sys.modules and 'ray' not in sys.modules; "
        "print(sorted(n for n in rllock.__all__ if callable(getattr(rllock, n))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == str(
        ["generate", "load_guide", "load_policy", "make_task", "read_assembly", "solve", "verify"]
    )


def test_api_solve_returns_verified_assemblies():
    import rllock

    task = rllock.make_task("cube4", 7)
    found = rllock.solve(task, count=2, time_limit=30, seed=1)
    assert len(found) == 2 and all(rllock.verify(a).valid for a in found)
    assert not (found[0] == found[1]).all()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    add_flags(p, TrainConfig, required_unless="--resume")
    return p


def test_flags_come_from_the_config_with_their_docstrings():
    parser = _parser()
    helps = {a.dest: a.help for a in parser._actions}
    assert "Simulations per decision" in helps["simulations"]  # a nested field, flat flag
    assert helps["evaluation"].startswith(field_docs(SelfPlayConfig)["evaluation"][:40])
    args = parser.parse_args(
        [
            "--shape",
            "cube5",
            "--pieces",
            "13",
            "--features",
            "8,16",
            "--simulations",
            "32",
            "--no-symmetries",
            "--episodes-per-batch",
            "4",
            "--max-learner-steps",
            "7",
        ]
    )
    config = from_flags(TrainConfig, args)
    assert config.net == NetConfig(features=(8, 16)) and config.mcts == MCTSConfig(simulations=32)
    assert config.learner.symmetries is False and config.selfplay.episodes_per_batch == 4
    assert config.max_learner_steps == 7 and config.net.canvas is None


def test_the_saved_config_round_trips():
    config = TrainConfig(
        shape="ring",
        pieces=15,
        net=NetConfig(canvas=8, features=(4, 8)),
        mcts=MCTSConfig(candidates=16),
        selfplay=SelfPlayConfig(actors=3),
    )
    assert from_json(TrainConfig, to_json(config)) == config


def test_version_one_checkpoints_flat_settings_become_the_nested_config():
    flat = {
        "shape": "cube4",
        "pieces": 8,
        "canvas": 4,
        "features": [8, 16],
        "simulations": 64,
        "actors": 2,
        "episodes_per_batch": 4,
        "learning_rate": 3e-4,
        "min_buffer": 256,
        "unknown_old_field": 1,
    }
    config = from_flat(TrainConfig, flat)
    assert config.net == NetConfig(canvas=4, features=(8, 16)) and config.mcts.simulations == 64
    assert config.selfplay == SelfPlayConfig(actors=2, episodes_per_batch=4)
    assert config.learner.learning_rate == 3e-4 and config.min_buffer == 256


def test_layouts_give_each_actor_its_share_of_the_cores():
    from rllock.orchestration.pool import plan_layout

    per_actor = plan_layout(SelfPlayConfig(), cpus=16, gpus=0, reserved_cpus=1)
    assert (per_actor.actors, per_actor.threads, per_actor.groups, per_actor.mode) == (15, 1, 1, "per-actor")
    one = plan_layout(SelfPlayConfig(actors=1), cpus=2, gpus=0, reserved_cpus=0)
    assert (one.cpus, one.threads, one.groups) == (2, 2, 2)
    crowded = plan_layout(SelfPlayConfig(actors=4), cpus=2, gpus=0, reserved_cpus=1)
    assert crowded.cpus == 0.25 and crowded.threads == 1  # more actors than cores: they share
    gpu = plan_layout(SelfPlayConfig(), cpus=16, gpus=1, reserved_cpus=1)
    assert (gpu.mode, gpu.actors, gpu.episodes, gpu.gpus, gpu.groups) == ("lockstep", 1, 15 * 8, 1.0, 1)
    cluster = plan_layout(
        SelfPlayConfig(evaluation="lockstep"), cpus=64, gpus=1, reserved_cpus=1, node_cpus=16
    )
    assert cluster.cpus == 16 and cluster.threads == 16  # one worker fits on one node
    # an actor runs on one node: two 1-CPU worker nodes give one actor 1 CPU, not 2
    spread = plan_layout(SelfPlayConfig(actors=1), cpus=2, gpus=0, reserved_cpus=0, node_cpus=1)
    assert (spread.cpus, spread.threads) == (1, 1)


def test_the_folders_are_installed_inside_rllock_under_no_generic_name():
    """actors/, learner/ and orchestration/ are imported only as rllock.actors and so on (the links in
    rllock/ point at them), never by a bare name that could shadow another package in a user's
    environment; the wheel installs `rllock` alone."""
    for folder in ("actors", "learner", "orchestration"):
        link = ROOT / "rllock" / folder
        assert link.is_symlink() and link.resolve() == (ROOT / folder).resolve(), link
    bare = {
        f"{path.relative_to(ROOT)}: {m}"
        for package in PACKAGES
        for path in _sources(package)
        for m, _ in _import_statements(path, _module_name(path))
        if m.split(".")[0] in ("actors", "learner", "orchestration", "cluster")
    }
    assert bare == set()
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'include = ["rllock*"]' in pyproject
    assert 'rllock = "rllock.orchestration.cli.main:entry"' in pyproject
