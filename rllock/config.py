"""Every program's typed configuration, in one light module (no JAX or Ray imports), so that the
command line can build its parser, and tests their settings, without loading the machinery."""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

from rllock.errors import RLLockError


@dataclass(frozen=True)
class NetConfig:
    canvas: int = 8
    """Side of the cubic canvas; smaller shapes are padded, larger ones are an error."""
    features: tuple[int, ...] = (16, 32, 64)
    """Channels per U-Net level; each level halves the resolution."""
    value_hidden: int = 64


@dataclass(frozen=True)
class MCTSConfig:
    simulations: int = 256
    """Simulations per decision."""
    max_considered: int = 16
    """Gumbel MuZero's max_num_considered_actions at the root."""
    raw_samples: int = 1024
    """M_s: raw chunks sampled when a node is expanded."""
    candidates: int = 32
    """M_c: accepted chunks kept as a node's candidate actions."""
    gumbel_scale: float = 1.0


@dataclass(frozen=True)
class LearnerConfig:
    learning_rate: float = 5e-5
    """Adam's learning rate (the paper's 5e-5)."""
    batch_size: int = 64
    """Transitions per update."""
    symmetries: bool = True
    """Map each sampled transition through a random symmetry of the shape (see topology.symmetries)."""


@dataclass(frozen=True)
class TrainConfig:
    shape: str
    """Built-in name or shape file."""
    pieces: int
    """K."""
    removal: str = "straight"
    resolution: int | None = None
    """For mesh shapes: voxels along the longest side."""
    actors: int = 0
    """Self-play actors; 0 = one per CPU core left after the learner's."""
    minutes: float = 10.0
    """Wall-clock training time (on resume: the time to add)."""
    logdir: str = "runs/latest"
    seed: int = 0
    address: str | None = None
    """Join this Ray cluster instead of starting a local Ray instance."""
    canvas: int = 8
    features: tuple[int, ...] = (16, 32, 64)
    simulations: int = 256
    max_considered: int = 16
    raw_samples: int = 1024
    candidates: int = 32
    episodes_per_batch: int = 8
    learning_rate: float = 5e-5
    batch_size: int = 64
    buffer_capacity: int = 50_000
    """Transitions kept; the oldest are overwritten."""
    min_buffer: int = 256
    """Transitions in the buffer before the learner starts."""
    success_fraction: float = 0.0
    """Share of each mini-batch drawn from successful episodes' transitions, while there are any
    (self-imitation, for tasks where successes are rare); 0 = uniform replay, as in the paper."""
    symmetries: bool = True
    """Augment mini-batches with the shape's symmetries (axis permutations and reflections)."""
    replay_ratio: float = 4.0
    """At most this many sampled transitions per transition produced by self-play."""
    publish_every: int = 25
    """Learner steps between weight versions."""
    max_policy_lag: int = 4
    """Weight versions an in-flight self-play batch may fall behind before the learner waits."""
    validate_minutes: float = 5.0
    validation_episodes: int = 64
    checkpoint_minutes: float = 2.0

    def net(self) -> NetConfig:
        return NetConfig(canvas=self.canvas, features=tuple(self.features))

    def mcts(self) -> MCTSConfig:
        return MCTSConfig(simulations=self.simulations, max_considered=self.max_considered,
                          raw_samples=self.raw_samples, candidates=self.candidates)

    def learner(self) -> LearnerConfig:
        return LearnerConfig(learning_rate=self.learning_rate, batch_size=self.batch_size,
                             symmetries=self.symmetries)

    def validate(self) -> None:
        """Bad settings are one-line errors here, not tracebacks deep inside a run."""
        positive = ("minutes", "canvas", "simulations", "max_considered", "raw_samples", "candidates",
                    "episodes_per_batch", "learning_rate", "batch_size", "buffer_capacity", "replay_ratio",
                    "publish_every", "max_policy_lag", "validate_minutes", "validation_episodes",
                    "checkpoint_minutes")
        for name in positive:
            if not getattr(self, name) > 0:
                raise RLLockError(f"--{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if self.actors < 0 or self.min_buffer < 0 or not self.features or min(self.features) < 1:
            raise RLLockError("--actors and --min-buffer must be >= 0 and --features positive")
        if not 0.0 <= self.success_fraction <= 1.0:
            raise RLLockError(f"--success-fraction must lie in [0, 1], got {self.success_fraction}")
        if self.batch_size > self.buffer_capacity:
            raise RLLockError("--batch-size cannot exceed --buffer-capacity")
        if Path(self.logdir).exists() and not Path(self.logdir).is_dir():
            raise RLLockError(f"--logdir {self.logdir} is a file")

    @staticmethod
    def from_json(doc: dict) -> "TrainConfig":
        known = {f.name for f in fields(TrainConfig)}
        values = {k: v for k, v in doc.items() if k in known}
        values["features"] = tuple(values.get("features", (16, 32, 64)))
        return TrainConfig(**values)
