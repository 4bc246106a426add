"""MCTS over action chunks: mctx's Gumbel MuZero, with nodes expanded on the host by the compiled sampler.

The search tree (inside jit) holds only integer handles into a host-side `rllock.search.nodes.NodeStore`.
Expanding a leaf calls back to the host (`jax.experimental.io_callback`, `expand_rows`): the store applies
the chunk, samples M_s raw chunks for the child, keeps M_c accepted ones as its candidate actions, and
returns the child's planes and candidates; the network then scores all leaves of the batch in one call.
Several episodes run in lockstep, one batch row each, so every simulation is one network call for them all.

Rewards: 1/K per accepted chunk. A child with no candidates (a dead end) or with K-1 pieces placed
(success) is terminal: discount 0 and value 0. Expanding below a terminal node gives reward 0.
A non-terminal child's value is known to lie in [1/K, (K-1-i)/K] (it has an accepted candidate, and
i pieces are placed), so the network's estimate is clipped to that range (`bounded_value`): even an
untrained network then tells a live child from a dead end one level earlier.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
import mctx
import numpy as np
from jax.experimental import io_callback

from rllock.config import MCTSConfig, NetConfig
from rllock.core.env import (
    State,
    Task,
    apply_chunk,
    candidates_many,
    initial_state,
    is_solved,
)
from rllock.search.base import Episode, Player, TimeSplit, derive_seed, group_sizes
from rllock.search.network import PolicyValueNet, chunk_logits, planes_of
from rllock.search.nodes import NodeStore, node_features, record_episode


class ChunkStore(NodeStore):
    """RL-Lock's actions: whole pieces, M_c accepted chunks per node drawn by the compiled sampler."""

    @staticmethod
    def action_shape(task: Task, config: MCTSConfig) -> tuple[int, int]:
        return config.candidates, task.piece_size

    def initial(self) -> State:
        return initial_state(self.task)

    def candidates(self, states: list) -> list[np.ndarray]:
        seeds = self.rng.integers(1 << 31, size=len(states))
        cands = [np.zeros((0, self.task.piece_size), np.int32)] * len(states)
        live = [i for i, s in enumerate(states) if not is_solved(self.task, s)]
        if live:
            start = time.perf_counter()
            found, _ = candidates_many(
                self.task,
                [states[i] for i in live],
                seeds[live],
                num_samples=self.config.raw_samples,
                max_candidates=self.config.candidates,
                parallel=self.parallel,
            )
            self.times.sampling += time.perf_counter() - start
            for i, c in zip(live, found):
                cands[i] = c
        return cands

    def apply(self, state: State, action: np.ndarray) -> State:
        return apply_chunk(state, action)

    def floor(self, reward: float) -> float:
        # A live child has an accepted candidate: one more piece is certain.
        return 1.0 / self.task.pieces


def expand_rows(store: NodeStore, nodes: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, ...]:
    """One simulation's expansion for every row: (child nodes, reward, discount, value floor and cap,
    and the children's features). A row below a terminal node stays where it is, with reward 0. Its
    time counts as the store's host time, less what the sampler took of it."""
    start, sampled = time.perf_counter(), store.times.sampling
    out = _expand(store, nodes.tolist(), actions.tolist())
    store.times.host += time.perf_counter() - start - (store.times.sampling - sampled)
    return out


def _expand(store: NodeStore, nodes: list[int], actions: list[int]) -> tuple[np.ndarray, ...]:
    moves = [
        r for r, (n, a) in enumerate(zip(nodes, actions)) if not store.terminal(n) and a < len(store.cands[n])
    ]
    kids = np.array(nodes, np.int32)
    kids[moves] = store.children_of([(nodes[r], actions[r]) for r in moves])
    reward = np.zeros(len(nodes), np.float32)
    discount = np.zeros(len(nodes), np.float32)
    floor = np.zeros(len(nodes), np.float32)
    cap = np.zeros(len(nodes), np.float32)
    k = store.task.pieces
    for r in moves:
        kid, parent = store.states[int(kids[r])], store.states[nodes[r]]
        reward[r] = (kid.placed - parent.placed) / k
        discount[r] = 0.0 if store.terminal(int(kids[r])) else 1.0
        floor[r] = store.floor(float(reward[r]))
        cap[r] = (k - 1 - kid.placed) / k
    planes, chunks, valid = node_features(store, kids)
    return kids, reward, discount, floor, cap, planes, chunks, valid


def bounded_value(value: jax.Array, discount: jax.Array, floor: jax.Array, cap: jax.Array) -> jax.Array:
    """The network's value clipped to what is known of a child: 0 when terminal; otherwise at least
    `floor` (`NodeStore.floor`: 1/K for a chunk node, which has an accepted candidate) and at most
    `cap` ((K-1-i)/K, the pieces still to place)."""
    return jnp.where(discount > 0, jnp.clip(value, floor, cap), 0.0)


def _expansion_shapes(
    batch: int, action_shape: tuple[int, int], canvas: int, planes: int
) -> tuple[jax.ShapeDtypeStruct, ...]:
    """What `expand_rows` returns for `batch` rows, as the host callback must declare it."""
    (m, n), c = action_shape, canvas
    return (
        jax.ShapeDtypeStruct((batch,), jnp.int32),
        jax.ShapeDtypeStruct((batch,), jnp.float32),
        jax.ShapeDtypeStruct((batch,), jnp.float32),
        jax.ShapeDtypeStruct((batch,), jnp.float32),
        jax.ShapeDtypeStruct((batch,), jnp.float32),
        jax.ShapeDtypeStruct((batch, c, c, c, planes), jnp.float32),
        jax.ShapeDtypeStruct((batch, m, n), jnp.int32),
        jax.ShapeDtypeStruct((batch, m), jnp.bool_),
    )


class CompiledSearch:
    """One compiled batched search (the network's canvas, M, n, the batch size), shared by every
    `Searcher` of that shape: each lockstep group of a process plays through the same program, so it is
    compiled once, not once per group. The host callback finds the calling searcher's node store by the
    slot it passes in (searchers run in threads of their own, the callback on XLA's)."""

    def __init__(
        self, net: PolicyValueNet, config: MCTSConfig, space: type[NodeStore], task: Task, batch: int
    ):
        self.net = net
        self.config = config
        self.space = space
        self.canvas = net.config.canvas_side()
        self.batch = batch
        # Weak: a store lives as long as the play that made it, not as long as this shared program.
        self.stores: weakref.WeakValueDictionary[int, NodeStore] = weakref.WeakValueDictionary()
        self._shapes = _expansion_shapes(
            batch, space.action_shape(task, config), self.canvas, planes_of(net.config)
        )
        self._jitted = jax.jit(self._tree_search)
        self._compiled: Any = None
        self._lock = threading.Lock()
        self._slots = 0

    def new_slot(self) -> int:
        """A slot for one more searcher's node store."""
        with self._lock:
            self._slots += 1
            return self._slots - 1

    def run(self, slot: int, params, key, roots, planes, chunks, valid):
        """The search for the searcher in `slot`; compiled ahead of time on the first call, under a lock,
        so that groups starting together do not compile it each."""
        args = ((params, jnp.int32(slot)), key, roots, planes, chunks, valid)
        with self._lock:
            if self._compiled is None:
                self._compiled = self._jitted.lower(*args).compile()
        return self._compiled(*args)

    def _evaluate(self, params, planes, chunks, valid):
        voxel_logits, value = self.net.apply({"params": params}, planes)
        return chunk_logits(voxel_logits, chunks, valid), value

    def _host_expand(self, slot, nodes, actions):
        return expand_rows(self.stores[int(slot)], np.asarray(nodes), np.asarray(actions))

    def _recurrent(self, params_slot, rng_key, action, embedding):
        """mctx's recurrent function: the leaves are expanded on the host, then scored in one call."""
        del rng_key
        params, slot = params_slot
        kids, reward, discount, floor, cap, planes, chunks, valid = io_callback(
            self._host_expand, self._shapes, slot, embedding, action
        )
        logits, value = self._evaluate(params, planes, chunks, valid)
        out = mctx.RecurrentFnOutput(
            reward=reward,
            discount=discount,
            prior_logits=logits,
            value=bounded_value(value, discount, floor, cap),
        )
        return out, kids

    def _tree_search(self, params_slot, key, roots, planes, chunks, valid):
        logits, value = self._evaluate(params_slot[0], planes, chunks, valid)
        root = mctx.RootFnOutput(prior_logits=logits, value=value, embedding=roots)
        out = mctx.gumbel_muzero_policy(
            params_slot,
            key,
            root,
            self._recurrent,
            num_simulations=self.config.simulations,
            invalid_actions=~valid,
            max_depth=self.config.max_depth,
            max_num_considered_actions=self.config.max_considered,
            gumbel_scale=self.config.gumbel_scale,
        )
        return out.action, out.action_weights, value


class SharedSearches:
    """The compiled searches of a process, by shape (network, search settings, action space, M x n,
    batch), the least recently used beyond `limit` let go: tracing, lowering and loading a search is
    slow, and a process asks for the same shape again and again (each validation of a run, every
    checkpoint a bench compares, each job of the service)."""

    def __init__(self, limit: int):
        self.limit = limit
        self._found: OrderedDict[tuple, CompiledSearch] = OrderedDict()
        self._lock = threading.Lock()

    def get(
        self, net: NetConfig, config: MCTSConfig, space: type[NodeStore], task: Task, batch: int
    ) -> CompiledSearch:
        key = (net, config, space, space.action_shape(task, config), batch)
        with self._lock:
            found = self._found.get(key)
            if found is None:
                found = self._found[key] = CompiledSearch(PolicyValueNet(net), config, space, task, batch)
                while len(self._found) > self.limit:
                    self._found.popitem(last=False)
            self._found.move_to_end(key)
            return found


SHARED = SharedSearches(16)


class Searcher:
    """A batched search for one task and action space, through a `CompiledSearch` of its shape (its own,
    or one shared with other searchers); `play` gives it a fresh store of kind `space` per batch."""

    def __init__(
        self,
        net: PolicyValueNet,
        config: MCTSConfig,
        space: type[NodeStore],
        task: Task,
        batch: int,
        compiled: CompiledSearch | None = None,
    ):
        self.compiled = SHARED.get(net.config, config, space, task, batch) if compiled is None else compiled
        self.batch = batch
        self.slot = self.compiled.new_slot()

    def play(
        self,
        params,
        task: Task,
        key: jax.Array,
        *,
        seed: int,
        times: TimeSplit | None = None,
        parallel: bool = True,
    ) -> list[Episode]:
        """`batch` episodes in lockstep from the empty state; each decision takes the search's
        action. `times`, when given, accumulates where the time went; `parallel`: see `NodeStore`."""
        c = self.compiled
        store = c.space(task, c.config, c.canvas, seed, parallel, task_planes=c.net.config.task_planes)

        def decide(sub: jax.Array, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            actions, weights, _ = self.search(params, sub, store, nodes)
            return actions, weights

        return play_lockstep(store, self.batch, decide, key, times)

    def search(self, params, key: jax.Array, store: NodeStore, roots: np.ndarray):
        """(actions [B], search policy pi [B, M], root values [B]) for the root nodes `roots`."""
        self.compiled.stores[self.slot] = store
        start, before = time.perf_counter(), store.times.sampling + store.times.host
        planes, chunks, valid = node_features(store, roots)
        # A finished episode's row still runs (fixed batch shape); one valid dummy action keeps it finite.
        valid[~valid.any(axis=1), 0] = True
        action, weights, value = self.compiled.run(
            self.slot, params, key, jnp.asarray(roots, jnp.int32), planes, chunks, valid
        )
        action, weights, value = np.asarray(action), np.asarray(weights), np.asarray(value)
        store.times.network += (
            time.perf_counter() - start - (store.times.sampling + store.times.host - before)
        )
        return action, weights, value


def play_lockstep(
    store: NodeStore,
    batch: int,
    decide: Callable[[jax.Array, np.ndarray], tuple[np.ndarray, np.ndarray]],
    key: jax.Array,
    times: TimeSplit | None,
) -> list[Episode]:
    """`batch` episodes in lockstep from the store's initial state: `decide(key, nodes)` gives every
    row's action and its policy over the node's candidates (rows that have ended are ignored)."""
    nodes = np.array(store.add_many([store.initial() for _ in range(batch)]), np.int32)
    trace: list[list[tuple[int, np.ndarray, int]]] = [[] for _ in range(batch)]
    active = np.array([not store.terminal(n) for n in nodes])
    while active.any():
        key, sub = jax.random.split(key)
        actions, weights = decide(sub, nodes)
        rows = np.flatnonzero(active)
        for b in rows:
            trace[b].append((int(nodes[b]), weights[b], int(actions[b])))
        nodes[rows] = store.children_of([(int(nodes[b]), int(actions[b])) for b in rows])
        active[rows] = [not store.terminal(int(nodes[b])) for b in rows]
    if times is not None:
        times.add(store.times)
    return [record_episode(store, trace[b], int(nodes[b])) for b in range(batch)]


def play_groups(
    searchers: Sequence[Player],
    params,
    task: Task,
    key: jax.Array,
    *,
    seed: int,
    times: TimeSplit | None = None,
) -> list[Episode]:
    """Several lockstep groups (one per searcher) played at once, one thread each: while one group's
    network runs in XLA, another's sampler runs in numba, both without the GIL, so a worker with T cores
    keeps them all busy with T groups. One group runs on its own with the sampler spread over numba's
    threads. Group g uses key fold_in(key, g) and node seed derive_seed(seed, g); `times` sums over the groups
    (thread-seconds)."""
    if len(searchers) == 1:
        return searchers[0].play(params, task, key, seed=seed, times=times)
    splits = [TimeSplit() for _ in searchers]

    def group(g: int) -> list[Episode]:
        return searchers[g].play(
            params,
            task,
            jax.random.fold_in(key, g),
            seed=derive_seed(seed, g),
            times=splits[g],
            parallel=False,
        )

    with ThreadPoolExecutor(len(searchers)) as pool:
        episodes = [e for batch in pool.map(group, range(len(searchers))) for e in batch]
    if times is not None:
        for split in splits:
            times.add(split)
    return episodes


def searchers(
    net: NetConfig, config: MCTSConfig, space: type[NodeStore], task: Task, episodes: int, groups: int
) -> list[Searcher]:
    """A searcher per lockstep group, for `episodes` split into `groups` (see `play_groups`); groups of
    one size share one compiled search (`SHARED`)."""
    return [
        Searcher(PolicyValueNet(net), config, space, task, size) for size in group_sizes(episodes, groups)
    ]
