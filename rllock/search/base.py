"""The contract types that the searches, the self-play actors and the learner share (as mctx's
`_src/base.py`): what a played episode is, who plays them, where search time goes, and how seeds of
independent streams are derived. Light on purpose: numpy only, so that the replay buffer and the actors
can name these types without loading JAX.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    import jax

    from rllock.core.env import Task


@dataclass
class TimeSplit:
    """Where search time goes: the compiled sampler, the rest of the host callbacks (applying chunks,
    encoding planes), and everything else inside the jitted search (the network and mctx's tree)."""

    sampling: float = 0.0
    host: float = 0.0
    network: float = 0.0

    def add(self, other: TimeSplit) -> None:
        self.sampling += other.sampling
        self.host += other.host
        self.network += other.network


@dataclass(frozen=True)
class Episode:
    """One self-play episode, compact: states as labels, candidate actions as voxel numbers."""

    labels: np.ndarray  # int8/int16[T, N] (env.compact_dtypes): the state before each decision
    placed: np.ndarray  # int16[T]: the `placed` its encoding is given (NodeStore.encoded_placed)
    chunks: np.ndarray  # int16/int32[T, M, n] (env.compact_dtypes): candidate voxel numbers, 0-padded
    num_valid: np.ndarray  # int16[T]: how many candidates are real
    pi: np.ndarray  # float32[T, M]: the search policy
    z: np.ndarray  # float32[T]: cumulative reward from each state to the end
    success: bool
    final: Any  # the last state reached (env.State, or voxel_env.VoxelState for voxel actions)
    actions: np.ndarray  # int16[T]: the candidate taken (what PPO learns from)


@dataclass(frozen=True)
class BufferCounts:
    """A replay buffer's counts, as it reports them after taking a batch."""

    size: int  # transitions held
    added: int  # transitions ever added
    successes: int  # held transitions of successful episodes
    received_bytes: int  # the array bytes of every episode it was sent
    peak_rss_mb: float  # its process's peak resident memory


class Player(Protocol):
    """Plays lockstep batches of `batch` episodes: a `Searcher`, or PPO's `rllock.search.ppo.PolicyPlayer`."""

    batch: int

    def play(
        self,
        params,
        task: Task,
        key: jax.Array,
        *,
        seed: int,
        times: TimeSplit | None = None,
        parallel: bool = True,
    ) -> list[Episode]: ...


def derive_seed(*parts: int) -> int:
    """A seed for the stream named by `parts` (run seed, round, group...): distinct tuples give
    independent streams, unlike sums or products of the parts, which collide across rounds and groups."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0] >> 1)


def group_sizes(episodes: int, groups: int) -> list[int]:
    """`episodes` split into at most `groups` lockstep groups of nearly equal size."""
    groups = max(1, min(groups, episodes))
    return [episodes // groups + (g < episodes % groups) for g in range(groups)]
