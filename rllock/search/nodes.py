"""The search tree's node store on the host, and what is read off it: the network's features of a batch of
nodes, and the episode a sequence of decisions recorded.

A node is an integer handle (the batched search inside jit holds only those): its state and its candidate
actions live here, with the children already reached. What an action is, a store's subclass says:
`rllock.search.mcts.ChunkStore` (one whole piece, RL-Lock) and `rllock.search.voxel_search.VoxelStore`
(one voxel, RL-Lock_Action).
"""

from __future__ import annotations

import numpy as np

from rllock.config import MCTSConfig
from rllock.core.env import Task, compact_dtypes
from rllock.search.base import Episode, TimeSplit
from rllock.search.network import canvas_index, encode_batch


class NodeStore:
    """Search nodes on the host: states, candidate actions (as chunks of voxel numbers, [L, n]),
    children. Subclasses say what an action is. With `parallel`, a simulation's expansions are spread
    over numba's threads; without, they run on the calling thread (for several stores searched in
    threads of their own). `times` collects where the host time went, for whoever searches the store."""

    def __init__(
        self,
        task: Task,
        config: MCTSConfig,
        canvas: int,
        seed: int,
        parallel: bool = True,
        *,
        task_planes: bool = False,
    ):
        self.parallel = parallel
        self.task_planes = task_planes
        self.task = task
        self.config = config
        self.canvas_idx = canvas_index(task, canvas)
        self.canvas = canvas
        self.rng = np.random.default_rng(seed)
        self.states: list = []
        self.cands: list[np.ndarray] = []
        self.children: dict[tuple[int, int], int] = {}
        self.times = TimeSplit()
        self.m, self.n = self.action_shape(task, config)

    @staticmethod
    def action_shape(task: Task, config: MCTSConfig) -> tuple[int, int]:
        """(M, n): candidate actions per node at most, voxels per action."""
        raise NotImplementedError

    def initial(self):
        """The state an episode starts from."""
        raise NotImplementedError

    def candidates(self, states: list) -> list[np.ndarray]:
        """Each state's candidate actions, int32[L, n] (L = 0: terminal)."""
        raise NotImplementedError

    def apply(self, state, action: np.ndarray):
        raise NotImplementedError

    def encoded_placed(self, state) -> int:
        """The `placed` the network's encoding is given for `state` (`rllock.search.network.encode_batch`)."""
        return state.placed

    def floor(self, reward: float) -> float:
        """What a live child reached with `reward` is known to be worth at least
        (`rllock.search.mcts.bounded_value`)."""
        return 0.0

    def add_many(self, states: list) -> list[int]:
        """Store `states` as nodes, with their candidates; their numbers."""
        cands = self.candidates(states)
        first = len(self.states)
        self.states.extend(states)
        self.cands.extend(cands)
        return list(range(first, len(self.states)))

    def add(self, state) -> int:
        return self.add_many([state])[0]

    def terminal(self, node: int) -> bool:
        return len(self.cands[node]) == 0

    def child(self, node: int, action: int) -> int:
        """The node reached by taking candidate `action` (memoised, so a node is expanded once)."""
        return self.children_of([(node, action)])[0]

    def children_of(self, pairs: list[tuple[int, int]]) -> list[int]:
        """The nodes reached by (node, candidate action) pairs, expanding the new ones together."""
        new = list(dict.fromkeys(p for p in pairs if p not in self.children))
        if new:
            kids = self.add_many([self.apply(self.states[n], self.cands[n][a]) for n, a in new])
            self.children.update(zip(new, kids))
        return [self.children[p] for p in pairs]


def node_features(store: NodeStore, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The network's input for `nodes`: (planes [B, C, C, C, P], candidate actions as canvas indices
    [B, M, n], valid [B, M])."""
    labels = np.stack([store.states[i].labels for i in nodes])
    placed = np.array([store.encoded_placed(store.states[i]) for i in nodes])
    chunks = np.zeros((len(nodes), store.m, store.n), np.int32)
    valid = np.zeros((len(nodes), store.m), bool)
    for row, i in enumerate(nodes):
        c = store.cands[i]
        chunks[row, : len(c)] = store.canvas_idx[c]
        valid[row, : len(c)] = True
    return encode_batch(store.task, labels, placed, store.canvas, store.task_planes), chunks, valid


def record_episode(store: NodeStore, steps: list[tuple[int, np.ndarray, int]], last: int) -> Episode:
    """The episode that took the decisions `steps` ((node, policy over its candidates, candidate taken)
    each) and ended at node `last`."""
    task = store.task
    t = len(steps)
    label_dtype, voxel_dtype = compact_dtypes(task)
    labels = np.zeros((t, task.size), label_dtype)
    placed = np.zeros(t, np.int16)
    encoded = np.zeros(t, np.int16)
    chunks = np.zeros((t, store.m, store.n), voxel_dtype)
    num_valid = np.zeros(t, np.int16)
    pi = np.zeros((t, store.m), np.float32)
    actions = np.zeros(t, np.int16)
    for s, (node, weights, action) in enumerate(steps):
        state, cands = store.states[node], store.cands[node]
        labels[s] = state.labels
        placed[s] = state.placed
        encoded[s] = store.encoded_placed(state)
        chunks[s, : len(cands)] = cands
        num_valid[s] = len(cands)
        pi[s] = weights
        actions[s] = action
    final = store.states[last]
    # Only accepted pieces are rewarded (1/K each), so z_s = (placed at the end - placed at s) / K.
    z = ((final.placed - placed) / task.pieces).astype(np.float32)
    return Episode(labels, encoded, chunks, num_valid, pi, z, final.placed == task.pieces - 1, final, actions)
