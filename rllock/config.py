"""Every program's typed configuration, in one light module (no JAX or Ray imports), so that the
command line can build its parser, and tests their settings, without loading the machinery.

A training run has one `TrainConfig`, which nests the network, search, learner and self-play configs;
it is saved once, in every checkpoint's metadata, and that document is what both `--resume` and
`generate` read. The command line's flags are generated from these dataclasses
(`rllock.orchestration.cli.flags`), one flag per leaf field, with the field docstrings below as their help.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rllock.errors import RLLockError

EVALUATION_MODES = ("auto", "per-actor", "lockstep")
# What trains the network: see rllock.search.methods.
METHODS = ("rl-lock", "rl-lock-action", "ppo")


@dataclass(frozen=True)
class NetConfig:
    canvas: int | None = None
    """Side of the cubic canvas the network sees; default: the smallest that fits the shape (a
    multiple of 2^(levels-1)). The paper uses 8."""
    features: tuple[int, ...] = (16, 32, 64)
    """Channels per U-Net level; each level halves the resolution."""
    value_hidden: int = 64
    """Width of the value head's hidden layer."""
    task_planes: bool = False
    """Two more input planes that give the task's piece size n and K (on for multi-task training,
    --tasks: one network for many tasks)."""

    def levels_step(self) -> int:
        """The canvas side must be a multiple of this (each level halves it)."""
        return 1 << (len(self.features) - 1)

    def canvas_side(self) -> int:
        """The canvas side of a config that has one (`fitted`)."""
        if self.canvas is None:
            raise ValueError("the network config needs a concrete canvas (NetConfig.fitted)")
        return self.canvas

    def fitted(self, dims: tuple[int, ...]) -> NetConfig:
        """This config with a concrete canvas for a shape of `dims` (the smallest that fits, unless set)."""
        if self.canvas is not None:
            return self
        step = self.levels_step()
        return dataclasses.replace(self, canvas=-(-max(dims) // step) * step)


@dataclass(frozen=True)
class MCTSConfig:
    simulations: int = 256
    """Simulations per decision (the paper's 256)."""
    max_considered: int = 16
    """Gumbel MuZero's max_num_considered_actions at the root."""
    raw_samples: int = 1024
    """M_s: at most this many raw chunks are sampled when a node is expanded."""
    candidates: int = 32
    """M_c: sampling stops once this many distinct accepted chunks are found; they are the node's
    candidate actions."""
    gumbel_scale: float = 1.0
    """Scale of the Gumbel noise at the root (0 = deterministic search)."""
    max_depth: int | None = None
    """Deepest level a simulation descends to (default: unbounded; rl-lock-action: 32, the paper's)."""


@dataclass(frozen=True)
class LearnerConfig:
    learning_rate: float = 5e-5
    """Adam's learning rate (the paper's 5e-5)."""
    batch_size: int = 64
    """Transitions per update."""
    symmetries: bool = True
    """Map each sampled transition through a random symmetry of the shape (axis permutations and
    reflections)."""
    clip_ratio: float = 0.2
    """PPO only: the clipping range eps of the probability ratio."""
    value_coef: float = 0.5
    """PPO only: weight of the value loss."""
    entropy_coef: float = 0.01
    """PPO only: weight of the entropy bonus."""


@dataclass(frozen=True)
class SelfPlayConfig:
    actors: int = 0
    """Self-play actors; 0 = one per CPU core left after the learner's."""
    episodes_per_batch: int = 8
    """Episodes an actor plays in lockstep: each simulation evaluates all their leaves in one network
    call."""
    evaluation: str = "auto"
    """Where the network runs for self-play. per-actor: each actor on its own CPU core; lockstep: one
    worker with all the actors' episodes in one large lockstep batch, on the GPU when there is one, with
    the sampler spread over the cores; auto: lockstep when JAX sees a GPU, else per-actor (faster on
    CPUs)."""


@dataclass(frozen=True)
class TrainConfig:
    shape: str | None = None
    """Built-in name or shape file (a single-task run; or --tasks)."""
    pieces: int | None = None
    """K, the number of pieces (with --shape)."""
    tasks: str | None = None
    """Multi-task training, one network for many tasks: task groups SHAPE:KLO-KHI separated by commas,
    e.g. cube4:6-9,box:6x5x4:8-12,random:60-200:6-20 (random:NLO-NHI: a fresh random shape of that
    many voxels per draw; rllock.core.tasks). A group ending in @C plays on a C^3 canvas of its own,
    e.g. random:400-1000:30-80@16: one network for several canvases. Replaces --shape and --pieces."""
    init: str | None = None
    """Start from this checkpoint's network (a run's log directory or a shipped name, e.g. general:
    fine-tuning); its network size and input planes are used, and its canvas unless --canvas is given
    (the weights do not depend on the canvas side)."""
    removal: str = "straight"
    """straight: one axis slide per piece; path: DESIA's multi-move test."""
    method: str = "rl-lock"
    """rl-lock: MCTS over whole pieces (the paper's method); rl-lock-action: MCTS over single voxels (a
    baseline; unless given, 128 simulations and depth 32, the paper's settings for it); ppo: PPO over
    single voxels (a baseline; unless given, a 2,048-transition buffer, replay ratio 4, policy lag 1)."""
    resolution: int | None = None
    """For mesh shapes: voxels along the longest side."""
    minutes: float = 10.0
    """Wall-clock budget, a hard limit: the run returns within it plus 30 s, its last checkpoint
    included (on resume: the time to add)."""
    max_learner_steps: int | None = None
    """Stop after this many learner steps in all (default: only the time budget stops the run)."""
    logdir: str = "runs/latest"
    """Checkpoints, replay snapshots, TensorBoard events and the best assembly go here."""
    seed: int = 0
    """Seeds the network, the learner's sampling and every actor."""
    address: str | None = None
    """Join this Ray cluster instead of starting a local Ray instance."""
    buffer_capacity: int = 50_000
    """Transitions kept; the oldest are overwritten."""
    min_buffer: int | None = None
    """Transitions in the buffer before the learner starts (default: one batch)."""
    success_fraction: float = 0.0
    """Share of each mini-batch drawn from successful episodes' transitions, while there are any
    (self-imitation, for tasks where successes are rare); 0 = uniform replay, as in the paper."""
    replay_ratio: float = 4.0
    """At most this many sampled transitions per transition produced by self-play."""
    publish_every: int = 25
    """Learner steps between weight versions."""
    max_policy_lag: int = 4
    """Weight versions an in-flight self-play batch may fall behind before the learner waits."""
    validate_minutes: float = 5.0
    """Minutes between validations (fixed seeds, so scores compare across the run)."""
    validation_episodes: int = 64
    """Episodes per validation (the paper's 64)."""
    checkpoint_minutes: float = 2.0
    """Minutes between checkpoints; the first comes right after the first learner step."""
    net: NetConfig = field(default_factory=NetConfig)
    mcts: MCTSConfig = field(default_factory=MCTSConfig)
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    selfplay: SelfPlayConfig = field(default_factory=SelfPlayConfig)

    @property
    def warmup(self) -> int:
        """Transitions before learning starts."""
        return self.learner.batch_size if self.min_buffer is None else self.min_buffer

    def validate(self) -> None:
        """Bad settings are one-line errors here, not tracebacks deep inside a run."""
        positive = {
            "minutes": self.minutes,
            "simulations": self.mcts.simulations,
            "max_considered": self.mcts.max_considered,
            "raw_samples": self.mcts.raw_samples,
            "candidates": self.mcts.candidates,
            "episodes_per_batch": self.selfplay.episodes_per_batch,
            "learning_rate": self.learner.learning_rate,
            "batch_size": self.learner.batch_size,
            "buffer_capacity": self.buffer_capacity,
            "replay_ratio": self.replay_ratio,
            "publish_every": self.publish_every,
            "max_policy_lag": self.max_policy_lag,
            "validate_minutes": self.validate_minutes,
            "validation_episodes": self.validation_episodes,
            "checkpoint_minutes": self.checkpoint_minutes,
        }
        for name, value in positive.items():
            if not value > 0:
                raise RLLockError(f"--{name.replace('_', '-')} must be positive, got {value}")
        if self.tasks is not None and (self.shape is not None or self.pieces is not None):
            raise RLLockError("give either --tasks or --shape and --pieces, not both")
        if self.tasks is None and (self.shape is None or self.pieces is None):
            raise RLLockError("train needs --shape and --pieces, or --tasks (or --resume LOGDIR)")
        if self.tasks is not None and self.method != "rl-lock":
            raise RLLockError("--tasks trains the rl-lock method only")
        if self.pieces is not None and self.pieces < 2:
            raise RLLockError(f"--pieces must be at least 2, got {self.pieces}")
        if self.net.value_hidden < 1 or self.mcts.gumbel_scale < 0:
            raise RLLockError("--value-hidden must be at least 1 and --gumbel-scale at least 0")
        if self.net.canvas is not None and self.net.canvas < 1:
            raise RLLockError(f"--canvas must be positive, got {self.net.canvas}")
        if (
            self.selfplay.actors < 0
            or (self.min_buffer or 0) < 0
            or not self.net.features
            or min(self.net.features) < 1
        ):
            raise RLLockError("--actors and --min-buffer must be >= 0 and --features positive")
        if self.max_learner_steps is not None and self.max_learner_steps < 1:
            raise RLLockError(f"--max-learner-steps must be at least 1, got {self.max_learner_steps}")
        if not 0.0 <= self.success_fraction <= 1.0:
            raise RLLockError(f"--success-fraction must lie in [0, 1], got {self.success_fraction}")
        if self.learner.batch_size > self.buffer_capacity:
            raise RLLockError("--batch-size cannot exceed --buffer-capacity")
        if self.method not in METHODS:
            raise RLLockError(f"--method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.mcts.max_depth is not None and self.mcts.max_depth < 1:
            raise RLLockError(f"--max-depth must be at least 1, got {self.mcts.max_depth}")
        if self.selfplay.evaluation not in EVALUATION_MODES:
            raise RLLockError(
                f"--evaluation must be one of {', '.join(EVALUATION_MODES)}, got {self.selfplay.evaluation!r}"
            )
        if Path(self.logdir).exists() and not Path(self.logdir).is_dir():
            raise RLLockError(f"--logdir {self.logdir} is a file")


# Each baseline method's own settings, by leaf field name (flag names are leaf names): rl-lock-action
# searches with the paper's 128 simulations per voxel decision and depth 32 (its section 5); ppo learns
# near on-policy: a buffer of the freshest 2,048 transitions, each sampled about 4 times (as 4 epochs
# would), and self-play at most one weights version behind.
METHOD_DEFAULTS: dict[str, dict[str, Any]] = {
    "rl-lock": {},
    "rl-lock-action": {"simulations": 128, "max_depth": 32},
    "ppo": {"buffer_capacity": 2048, "replay_ratio": 4.0, "max_policy_lag": 1},
}


def with_method_defaults(config: TrainConfig, given: Collection[str]) -> TrainConfig:
    """`config` with its method's own settings (METHOD_DEFAULTS) for every leaf field not named in
    `given`: a setting the user gave always wins, even when it equals the general default. The command
    line passes the flags it was given; a program that builds its own config passes what it set."""
    return replace_leaves(
        config, {k: v for k, v in METHOD_DEFAULTS[config.method].items() if k not in set(given)}
    )


def replace_leaves(config: Any, values: dict[str, Any]) -> Any:
    """`config` with the leaf fields named in `values` (at any depth of nesting) replaced."""
    changes = {}
    for f in dataclasses.fields(config):
        sub = nested_config(f)
        if sub is not None:
            changes[f.name] = replace_leaves(getattr(config, f.name), values)
        elif f.name in values:
            changes[f.name] = values[f.name]
    return dataclasses.replace(config, **changes)


def to_json(config: Any) -> dict:
    """A config as a JSON-ready document (nested dataclasses become nested objects)."""
    return dataclasses.asdict(config)


def from_json(cls: type, doc: dict) -> Any:
    """The config of class `cls` saved by `to_json` (unknown keys are ignored, missing ones default)."""
    values = {}
    for f in dataclasses.fields(cls):
        if f.name not in doc:
            continue
        value = doc[f.name]
        sub = nested_config(f)
        if sub is not None:
            value = from_json(sub, value)
        elif isinstance(value, list):
            value = tuple(value)
        values[f.name] = value
    return cls(**values)


def from_flat(cls: type, doc: dict) -> Any:
    """The config of class `cls` from a flat document, one key per leaf field (how checkpoints of
    metadata version 1 saved the run's settings)."""
    values = {}
    for f in dataclasses.fields(cls):
        sub = nested_config(f)
        if sub is not None:
            values[f.name] = from_flat(sub, doc)
        elif f.name in doc:
            values[f.name] = tuple(doc[f.name]) if isinstance(doc[f.name], list) else doc[f.name]
    return cls(**values)


def nested_config(f: dataclasses.Field) -> type | None:
    """The nested config class of a field, or None for a leaf (the flags walk the same tree)."""
    factory = f.default_factory
    return factory if factory is not dataclasses.MISSING and dataclasses.is_dataclass(factory) else None


@dataclass(frozen=True)
class GuideConfig:
    window: int = 8
    """Side of the guide network's cubic window around the piece just placed (a multiple of 4)."""
    guide_features: tuple[int, ...] = (16, 32)
    """Channels of the window's two convolutions (each followed by a 2x2x2 pooling)."""
    guide_hidden: int = 64
    """Width of the hidden layers that join the window and the global features."""
    overview: bool = False
    """Also show the network the whole remaining volume: R and the placed pieces in R's bounding box,
    scaled down to the window's side (two more channels, their own convolutions)."""


GUIDE_LABELS = ("won", "reach")


@dataclass(frozen=True)
class GuideTrainConfig:
    """`rllock train-guide`: Ray actors run the search solver on a curriculum of random shapes, shipped
    shapes and K, every other search guided by the latest network; the children of a few states each
    search finished, labelled by rollouts (the share of the pieces left that plain searches from a child
    place), train the guide network (`rllock.search.guide`). The defaults of the labels and the learner
    are those every kept run and shipped guide was made with (data/replay/*.json)."""

    minutes: float = 10.0
    """Wall-clock budget, a hard limit (on resume: the time to add)."""
    max_learner_steps: int | None = None
    """Stop after this many learner steps in all (default: only the time budget stops the run)."""
    logdir: str = "runs/guide"
    """Checkpoints, the replay snapshot and TensorBoard events go here."""
    seed: int = 0
    """Seeds the network, the learner's sampling and the curriculum of every actor."""
    address: str | None = None
    """Join this Ray cluster instead of starting a local Ray instance."""
    actors: int = 0
    """Search actors; 0 = one per CPU core left after the learner's (at least one)."""
    search_seconds: float = 20.0
    """Seconds a search actor gives one curriculum task (it stops at the first assembly)."""
    probes: int = 2
    """States of each search (drawn among those it finished, `min_left` to `max_left` pieces before the
    end, dead ends passed over) whose children are labelled by rollouts and go to the replay buffer."""
    min_left: int = 3
    """The fewest pieces left at a probed state."""
    max_left: int = 20
    """The most pieces left at a probed state: where searches fail, the last pieces."""
    rollouts: int = 2
    """Plain searches from each child of a probed state; its value target is made from theirs (`label`)."""
    rollout_expansions: int = 256
    """Node expansions of one rollout (a few Luby restarts)."""
    label: str = "reach"
    """A child's value target: "won", the share of its rollouts that reach an assembly; "reach", the
    share of the pieces left that they place (an assembly 1), which still tells siblings apart where
    every rollout fails."""
    rank_weight: float = 0.0
    """The weight of the sibling loss beside the value loss (`rllock.learner.guide_learner`): how much the
    network learns to order the children of one node, which is what the search asks of it. Off by
    default: on what 30 minutes on 2 cores label, it overfits sooner than the value loss alone."""
    min_voxels: int = 100
    """The curriculum's smallest random shape."""
    max_voxels: int = 2000
    """The curriculum's largest random shape."""
    max_pieces: int = 150
    """The curriculum's largest K (pieces have at least 4 voxels, K at least 5)."""
    cells: str = ""
    """Instead of the random curriculum, only these tasks, as `rllock bench guide --cells` writes them
    (mario:60,desia-bunny:80:path): a guide taught the tasks a user cannot solve."""
    edge: bool = False
    """With --cells: each cell's K moves after each of its searches, up (smaller pieces) after a solve and
    down after a failure, to the next K whose last piece is under twice the others (the hardest K of the
    next piece size: a K whose last piece takes many spare voxels is easy), within [K/2, N/4]; the
    searches sit at the shape's edge of failure, where rollouts tell children apart (where every
    search is solved, nearly every label is 1 and teaches nothing). Off: every cell keeps its K."""
    replay_from: str = ""
    """Instead of searching, train on replay snapshots already made, comma-separated: train-guide runs
    (their LOGDIR/replay.npz) or snapshot files. The learner alone, no Ray and no actors, on all their
    states at once, until --max-learner-steps or --minutes (the search and curriculum flags do nothing):
    networks trained so on the same states differ as much as whole runs do, at a fraction of the cost."""
    buffer_capacity: int = 200_000
    """States kept; the oldest are overwritten."""
    batch_size: int = 128
    """States per learner step."""
    guide_learning_rate: float = 1e-3
    """Adam's learning rate."""
    weight_average: float = 0.0
    """With a decay in (0, 1), e.g. 0.99: the actors, the held-out judgement and the checkpoints' guide
    use an exponential moving average of the learner's weights (the learner steps on its own), which
    moves less from one checkpoint to the next than the last step's weights do. 0: the last weights."""
    replay_ratio: float = 100.0
    """At most this many sampled states per state the searches produced: labels are dear (rollouts of
    every child) and few, so each is learned from many times."""
    publish_every: int = 50
    """Learner steps between weight versions handed to the actors."""
    checkpoint_minutes: float = 2.0
    """Minutes between checkpoints."""
    guide: GuideConfig = field(default_factory=GuideConfig)

    def validate(self) -> None:
        positive = {
            "minutes": self.minutes,
            "search_seconds": self.search_seconds,
            "probes": self.probes,
            "rollouts": self.rollouts,
            "rollout_expansions": self.rollout_expansions,
            "buffer_capacity": self.buffer_capacity,
            "batch_size": self.batch_size,
            "guide_learning_rate": self.guide_learning_rate,
            "replay_ratio": self.replay_ratio,
            "publish_every": self.publish_every,
            "checkpoint_minutes": self.checkpoint_minutes,
        }
        for name, value in positive.items():
            if not value > 0:
                raise RLLockError(f"--{name.replace('_', '-')} must be positive, got {value}")
        if not 0 <= self.weight_average < 1:
            raise RLLockError(f"--weight-average must be in [0, 1), got {self.weight_average}")
        if self.rank_weight < 0:
            raise RLLockError(f"--rank-weight must be >= 0, got {self.rank_weight}")
        if self.max_learner_steps is not None and self.max_learner_steps < 1:
            raise RLLockError(f"--max-learner-steps must be at least 1, got {self.max_learner_steps}")
        if self.edge and not self.cells:
            raise RLLockError("--edge moves the K of the tasks in --cells: give --cells too")
        if self.batch_size % 2:
            raise RLLockError(f"--batch-size must be even (pairs of siblings), got {self.batch_size}")
        if self.actors < 0:
            raise RLLockError(f"--actors must be >= 0, got {self.actors}")
        if self.label not in GUIDE_LABELS:
            raise RLLockError(f"--label must be one of {', '.join(GUIDE_LABELS)}, got {self.label!r}")
        if not 8 <= self.min_voxels <= self.max_voxels:
            raise RLLockError("--min-voxels must be at least 8 and at most --max-voxels")
        if not 1 <= self.min_left <= self.max_left:
            raise RLLockError("--min-left must be at least 1 and at most --max-left")
        if self.max_pieces < 5:
            raise RLLockError(f"--max-pieces must be at least 5, got {self.max_pieces}")
        if self.guide.window < 4 or self.guide.window % 4:
            raise RLLockError(f"--window must be a positive multiple of 4, got {self.guide.window}")
        if self.batch_size > self.buffer_capacity:
            raise RLLockError("--batch-size cannot exceed --buffer-capacity")
        if Path(self.logdir).exists() and not Path(self.logdir).is_dir():
            raise RLLockError(f"--logdir {self.logdir} is a file")


@dataclass(frozen=True)
class ServeConfig:
    """`rllock serve`: a Ray Serve application with an HTTP API and a web page; a model deployment that
    batches network evaluations across jobs, and a job runner with a queue."""

    host: str = "127.0.0.1"
    """Address the HTTP server listens on: loopback, unless you mean to serve other machines."""
    port: int = 8000
    """HTTP port."""
    address: str | None = None
    """Join this Ray cluster (HOST:PORT) instead of starting a local Ray instance."""
    data: str = "serve-data"
    """Folder for jobs and their files: they survive a restart of the server."""
    max_jobs: int = 0
    """Jobs that run at once (the rest wait in the queue); 0 = two per CPU core of the Ray cluster (a
    generate job waits for the network about half of its time)."""
    max_client_jobs: int = 16
    """Queued and running jobs one client address may have at once."""
    max_upload_mb: float = 20.0
    """Largest uploaded shape file, in MB."""
    max_voxels: int = 50_000
    """Largest shape, in voxels (after a mesh is voxelized)."""
    max_time_limit: float = 900.0
    """Largest time limit a job may ask for, in seconds."""

    def validate(self) -> None:
        if not 0 < self.port < 65536:
            raise RLLockError(f"--port must be 1-65535, got {self.port}")
        if self.max_jobs < 0:
            raise RLLockError(f"--max-jobs must be >= 0, got {self.max_jobs}")
        positive = {
            "max_client_jobs": self.max_client_jobs,
            "max_upload_mb": self.max_upload_mb,
            "max_voxels": self.max_voxels,
            "max_time_limit": self.max_time_limit,
        }
        for name, value in positive.items():
            if not value > 0:
                raise RLLockError(f"--{name.replace('_', '-')} must be positive, got {value}")
        if Path(self.data).exists() and not Path(self.data).is_dir():
            raise RLLockError(f"--data {self.data} is a file, not a folder")
