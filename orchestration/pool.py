"""Ray start-up and the trainers' actors: the self-play layout (how many actors, threads and episodes
each) and a pool of self-play actors with exactly one batch in flight per actor (shared by `rllock
train` and the bench), a pool of search actors (`rllock train-guide`) and none at all (a guide taught
replay snapshots already made). Each has what the loop (`rllock.orchestration.loop.Actors`) asks of actors."""

from __future__ import annotations

import logging
import os
import socket
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

import jax
import ray
from ray.exceptions import GetTimeoutError, RayActorError
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from rllock.actors.guide_actor import GuideActor, SearchReport, SearchTotals
from rllock.actors.selfplay import PlaySpec, PlayStats, SelfPlayActor, actor_env
from rllock.config import GuideTrainConfig, MCTSConfig, NetConfig, SelfPlayConfig
from rllock.errors import RLLockError
from rllock.search.workload import Workload

log = logging.getLogger(__name__)

PLACEMENT_TIMEOUT_S = 300.0
REACH_TIMEOUT_S = 5.0


def largest_node_cpus() -> float:
    return max((n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n.get("Alive")), default=1.0)


class _DropDefaultTokenNotice(logging.Filter):
    """Drops Ray's notice that a new local instance uses token authentication: Ray's default, the safe
    choice, and nothing to act on. Ray's other authentication warnings (such as a cluster joined without
    it) pass."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Token authentication is enabled for this Ray cluster")


_TOKEN_LOGGER = "ray._private.authentication.authentication_token_setup"


def _check_reachable(address: str) -> None:
    """A HOST:PORT that nothing answers on is one line at once: Ray itself retries for minutes."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or "/" in host:
        return  # "auto", or a URL (ray://, http://) that Ray resolves itself
    try:
        socket.create_connection((host, int(port)), timeout=REACH_TIMEOUT_S).close()
    except OSError as exc:
        raise RLLockError(f"cannot reach the Ray cluster at {address}: {exc.strerror or exc}") from None


def start_ray(address: str | None) -> bool:
    """Connect to Ray at `address` (or at RAY_ADDRESS, set inside a Ray job), else start a private local
    instance; True when this process started the instance (and so must shut it down). Ray starts its
    processes with fork(), so call this before JAX starts its threads (the first JAX array)."""
    if ray.is_initialized():
        return False
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        _check_reachable(address)
        ray.init(address=address, logging_level=logging.WARNING)
    else:
        notices = logging.getLogger(_TOKEN_LOGGER)
        if not any(isinstance(f, _DropDefaultTokenNotice) for f in notices.filters):
            notices.addFilter(_DropDefaultTokenNotice())
        # "local": Ray would otherwise join the last cluster `ray start` (or a test's Cluster) left on
        # this machine, a run of someone else's that our num_cpus cannot even be given to.
        ray.init(
            address="local", num_cpus=os.cpu_count(), include_dashboard=False, logging_level=logging.WARNING
        )
    return True


@dataclass(frozen=True)
class Layout:
    """How self-play runs: `actors` Ray actors, each with `episodes` lockstep episodes, `cpus` Ray CPUs,
    `threads` sampler threads and `gpus` Ray GPUs."""

    actors: int
    episodes: int
    cpus: float
    threads: int
    groups: int  # lockstep groups per actor, searched in threads of their own
    gpus: float
    mode: str  # "per-actor" or "lockstep"


def plan_layout(
    selfplay: SelfPlayConfig,
    *,
    cpus: float,
    gpus: float,
    reserved_cpus: float,
    node_cpus: float | None = None,
) -> Layout:
    """The layout for a cluster with `cpus` and `gpus` (`reserved_cpus` stay for the learner), whose
    largest node has `node_cpus` (default: all of them, one node).

    per-actor: `actors` actors (default one per free core), each on its share of the free cores, with one
    lockstep group per core. lockstep: one worker that plays all the actors' episodes in one lockstep
    batch, with the network on the GPU when there is one and the sampler spread over the free cores."""
    free = max(1.0, cpus - reserved_cpus)
    actors = selfplay.actors or max(1, int(free))
    mode = selfplay.evaluation
    if mode == "auto":
        mode = "lockstep" if gpus > 0 else "per-actor"
    if mode == "lockstep":
        gpu = 1.0 if gpus > 0 else 0.0
        worker = min(free, node_cpus or free)  # one worker: it must fit on one node
        return Layout(1, actors * selfplay.episodes_per_batch, worker, max(1, int(worker)), 1, gpu, mode)
    # Fractional when there are more actors than cores: they take turns. An actor runs on one node, so
    # it takes no more than the largest node has.
    share = min(free / actors, node_cpus or free)
    threads = max(1, int(share))
    return Layout(actors, selfplay.episodes_per_batch, share, threads, threads, 0.0, mode)


def publish(params: dict) -> list[ray.ObjectRef]:
    """A weights version for the actors: [one ObjectRef of the parameters], put in Ray's object store
    once and fetched by an actor only when its version changed."""
    return [ray.put(jax.device_get(params))]


class Calls:
    """Calls in flight on actors, one per actor, tagged by what each asked for. `wait` returns the calls
    that finished and those whose actor failed for good (Ray restarts a dead process and retries its call
    on its own, for actors made with max_restarts and max_task_retries); the caller replaces a failed
    actor. Only when more than `MAX_FAILURES_IN_A_ROW` calls fail with none finishing in between is it
    an error."""

    MAX_FAILURES_IN_A_ROW = 10

    def __init__(self) -> None:
        self.inflight: dict[ray.ObjectRef, tuple[Any, Any]] = {}  # call -> (actor, tag)
        self.failures_in_a_row = 0

    def submit(self, actor: Any, call: ray.ObjectRef, tag: Any) -> None:
        self.inflight[call] = (actor, tag)

    def wait(self, timeout: float | None) -> tuple[list[tuple[Any, Any, Any]], list[tuple[Any, Any, str]]]:
        """(finished: (actor, tag, result), failed: (actor, tag, why)) after waiting up to `timeout`
        seconds for one call."""
        ready, _ = ray.wait(list(self.inflight), num_returns=1, timeout=timeout)
        done, failed = [], []
        for ref in ready:
            actor, tag = self.inflight.pop(ref)
            try:
                result = ray.get(ref)
            except RayActorError as exc:
                why = str(exc).splitlines()[0]
                self.failures_in_a_row += 1
                if self.failures_in_a_row > self.MAX_FAILURES_IN_A_ROW:
                    raise RLLockError(
                        f"actors failed {self.failures_in_a_row} times in a row with no call finished "
                        f"(the last: {why}); see the log above"
                    ) from None
                failed.append((actor, tag, why))
                continue
            self.failures_in_a_row = 0
            done.append((actor, tag, result))
        return done, failed

    def cancel_all(self) -> None:
        for ref in self.inflight:
            ray.cancel(ref)

    def settle(self, seconds: float) -> None:
        """Wait up to `seconds` for the cancelled calls to end, and forget them."""
        refs = list(self.inflight)
        if refs:
            ray.wait(refs, num_returns=len(refs), timeout=seconds)
        self.inflight.clear()

    def __bool__(self) -> bool:
        return bool(self.inflight)


class ActorPool:
    """Self-play actors, each with one batch in flight, spread over the cluster's nodes.

    A dead actor process, or one whose node was lost, is restarted by Ray (on a node with room for it,
    once there is one: a node that joins later takes it) and its call retried; the pool notices the new
    process or node and logs it. An actor that fails for good is replaced by a new one; only when
    `Calls.MAX_FAILURES_IN_A_ROW` batches fail with none finishing in between does the pool give up.

    What an actor plays (the spec and the replay buffer's handle) is put in Ray's object store once and
    travels by reference with every call, not in the constructor: Ray does not keep an actor's
    constructor arguments alive for its restarts (ray-project/ray#53727), while a retried call brings
    its own arguments. The driver owns those objects, so they live as long as the driver's node."""

    def __init__(
        self,
        workload: Workload,
        net: NetConfig,
        mcts: MCTSConfig,
        method: str,
        layout: Layout,
        seed: int,
        buffer,
    ):
        self.options = dict(
            num_cpus=layout.cpus,
            num_gpus=layout.gpus,
            max_restarts=-1,
            max_task_retries=-1,
            # One actor per node before two on any: a lost node then takes the fewest actors with it.
            scheduling_strategy="SPREAD",
            runtime_env={"env_vars": actor_env(layout.threads, gpu=layout.gpus > 0)},
        )
        self.seed, self.started, self.layout = seed, 0, layout
        self.setup = [
            ray.put((PlaySpec(workload, net, mcts, method, layout.episodes, layout.groups), buffer))
        ]
        self.actors = [self._start() for _ in range(layout.actors)]
        self.number = {a: i + 1 for i, a in enumerate(self.actors)}  # for the log: actor 1, 2, ...
        try:
            places = ray.get([a.where.remote() for a in self.actors], timeout=PLACEMENT_TIMEOUT_S)
        except GetTimeoutError:
            raise RLLockError(
                f"the self-play actors could not start within {PLACEMENT_TIMEOUT_S:.0f} s: does a node "
                f"of the cluster have {layout.cpus:g} free CPUs{' and a GPU' if layout.gpus else ''}? "
                f"(see --actors, --evaluation)"
            ) from None
        self.places: dict = dict(zip(self.actors, places))
        log.info("self-play actors: %s", placement_summary([node for _, node in places]))
        self.calls = Calls()  # tagged with the weights version each batch plays
        self.displaced: set = set()  # actors whose node was lost, until they report from a new one

    def _start(self):
        """A new actor, with a seed of its own (a replacement does not replay its predecessor's games)."""
        self.started += 1
        # mypy skips class decorators: @ray.remote made SelfPlayActor an ActorClass, which has .options.
        return SelfPlayActor.options(**self.options).remote(self.seed + self.started - 1)  # type: ignore[attr-defined]

    def submit(self, actor, weights: list, version: int) -> None:
        self.calls.submit(actor, actor.run.remote(self.setup, weights, version), version)

    def submit_all(self, weights: list, version: int) -> None:
        for actor in self.actors:
            self.submit(actor, weights, version)

    def publish(self, params: dict) -> list[ray.ObjectRef]:
        return publish(params)

    def start(self, weights: list, version: int) -> None:
        self.submit_all(weights, version)

    def oldest_version(self) -> int | None:
        """The oldest weights version in flight, of the actors whose node is alive: an actor waiting for
        a node to restart on must not hold the learner back."""
        return min((v for a, v in self.calls.inflight.values() if a not in self.displaced), default=None)

    def node_lost(self, node: str) -> int:
        """Mark the actors that ran on `node` as waiting for a restart elsewhere; returns how many."""
        lost = {a for a, (_, where) in self.places.items() if where == node}
        self.displaced |= lost
        return len(lost)

    def collect(self, timeout: float, weights: list | None = None) -> list[tuple[object, PlayStats]]:
        """The batches finished within `timeout` seconds (at most one wait), with their actors. An actor
        that failed for good is replaced, and the replacement handed `weights` (the newest)."""
        done, failed = self.calls.wait(timeout)
        for actor, version, why in failed:
            self._replace(actor, why, weights, version)
        for actor, _, stats in done:
            self._note_place(actor, stats)
        return [(actor, stats) for actor, _, stats in done]

    def _note_place(self, actor, stats: PlayStats) -> None:
        before = self.places.get(actor)
        if before is None:
            log.info("self-play actor %d started on %s", self.number[actor], describe_node(stats.node))
        elif before[1] != stats.node:
            log.warning(
                "self-play actor %d restarted on %s (it ran on %s)",
                self.number[actor],
                describe_node(stats.node),
                describe_node(before[1]),
            )
        elif before[0] != stats.pid:
            number = self.number[actor]
            log.warning("self-play actor %d restarted (pid %d -> %d)", number, before[0], stats.pid)
        self.places[actor] = (stats.pid, stats.node)
        self.displaced.discard(actor)

    def _replace(self, actor, why: str, weights: list | None, version: int) -> None:
        number = self.number.pop(actor)
        self.places.pop(actor, None)
        self.displaced.discard(actor)
        self.actors.remove(actor)
        replacement = self._start()
        self.actors.append(replacement)
        self.number[replacement] = number
        log.error("self-play actor %d failed for good (%s); a new actor takes its place", number, why)
        if weights is not None:
            self.submit(replacement, weights, version)

    def alive(self) -> bool:
        return bool(self.calls)

    def nodes_in_use(self) -> set[str]:
        return {node for _, node in self.places.values()}

    def shutdown(self, settle_s: float = 10.0) -> None:
        """Stop every actor now; batches in flight are dropped. They are cancelled before their actors
        are killed: otherwise Ray counts each as a failed call to retry, and logs it."""
        self.calls.cancel_all()
        for actor in self.actors:
            ray.kill(actor)
        # ray.kill returns before the actors are gone: wait for the cancelled calls to end, so that a
        # ray.shutdown right after does not race their endings.
        self.calls.settle(settle_s)

    def stop(self) -> None:
        self.shutdown()


class SearchPool:
    """Search actors (`rllock.actors.guide_actor.GuideActor`), one core and one search in flight each: a
    finished actor is handed its next search with the newest weights and, with `--edge`, each cell's K as the
    totals hold it; one that failed for good is replaced. A search takes the weights it is handed when it
    starts, so there is no policy lag to bound."""

    def __init__(self, config: GuideTrainConfig, buffer: Any, totals: SearchTotals):
        self.config, self.buffer, self.totals = config, buffer, totals
        self.calls = Calls()  # tagged with the weights version each search was handed
        self.started = 0
        self.size = config.actors or max(1, int(ray.cluster_resources().get("CPU", 1)) - 1)

    def publish(self, params: dict) -> list[ray.ObjectRef]:
        return publish(params)

    def start(self, weights: list, version: int) -> None:
        for _ in range(self.size):
            self.submit(self._new_actor(), weights, version)
        log.info(
            "training the guide: %d search actor(s) for %g min; logs in %s",
            self.started,
            self.config.minutes,
            self.config.logdir,
        )

    def _new_actor(self) -> Any:
        """A new actor, with a seed of its own (a replacement does not repeat its predecessor's searches)."""
        self.started += 1
        seed = self.config.seed * 1000 + self.started + self.totals.searches
        options = dict(
            num_cpus=1, max_restarts=-1, max_task_retries=-1, runtime_env={"env_vars": actor_env(1)}
        )
        return GuideActor.options(**options).remote(seed, self.config)  # type: ignore[attr-defined]

    def submit(self, actor: Any, weights: list, version: int) -> None:
        edge = dict(self.totals.edge) or None
        self.calls.submit(actor, actor.run.remote(weights, version, self.buffer, edge), version)

    def collect(self, timeout: float, weights: list) -> list[tuple[Any, SearchReport]]:
        """The searches finished within `timeout` seconds (at most one wait), with their actors."""
        done, failed = self.calls.wait(timeout)
        for _, version, why in failed:
            log.error("search actor failed for good (%s); a new actor takes its place", why)
            self.submit(self._new_actor(), weights, version)
        return [(actor, report) for actor, _, report in done]

    def oldest_version(self) -> int | None:
        return None

    def stop(self) -> None:
        self.calls.cancel_all()  # searches under way are dropped: the budget is a hard limit


class NoActors:
    """A trainer without actors: the learner alone, on a replay buffer filled before the run."""

    def publish(self, params: dict) -> list:
        return []

    def start(self, weights: list, version: int) -> None:
        pass

    def collect(self, timeout: float, weights: list) -> list[tuple[Any, Any]]:
        time.sleep(timeout)  # nothing comes: wait as long as a call would have been waited for
        return []

    def submit(self, actor: Any, weights: list, version: int) -> None:
        raise AssertionError("no actor to hand a call")

    def oldest_version(self) -> int | None:
        return None

    def stop(self) -> None:
        pass


def describe_node(node_id: str) -> str:
    """ "node 1a2b3c4d (10.0.0.5)": the short id tells apart nodes that share an address."""
    address = next((n["NodeManagerAddress"] for n in ray.nodes() if n["NodeID"] == node_id), "?")
    return f"node {node_id[:8]} ({address})"


def placement_summary(nodes: list[str]) -> str:
    """ "2 on node 1a2b3c4d (10.0.0.5), 1 on node 9f8e7d6c (10.0.0.6)"."""
    counts = Counter(nodes)
    return ", ".join(f"{n} on {describe_node(node)}" for node, n in counts.most_common())


def driver_node() -> str:
    return ray.get_runtime_context().get_node_id()


def on_driver_node() -> NodeAffinitySchedulingStrategy:
    """Where an actor that writes into the run's folder must run: the driver's node, whose disk holds
    the folder, and which lives as long as the run."""
    return NodeAffinitySchedulingStrategy(node_id=driver_node(), soft=False)


def driver_node_cpus() -> float:
    node = driver_node()
    return next((n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n["NodeID"] == node), 0.0)


@dataclass
class NodeWatch:
    """Says when a node of the cluster is lost or joins (checked at most every `every_s` seconds)."""

    alive: set[str]
    every_s: float = 5.0
    next_check: float = 0.0

    @staticmethod
    def start() -> NodeWatch:
        return NodeWatch(alive_nodes())

    def check(self, now: float, pool: ActorPool) -> None:
        if now < self.next_check:
            return
        self.next_check = now + self.every_s
        alive = alive_nodes()
        for node in self.alive - alive:
            waiting = pool.node_lost(node)
            log.warning(
                "%s was lost%s",
                describe_node(node),
                f": its {waiting} self-play actor(s) restart on a node with room for them" if waiting else "",
            )
        for node in alive - self.alive:
            log.info("%s joined the cluster", describe_node(node))
        self.alive = alive


def alive_nodes() -> set[str]:
    return {n["NodeID"] for n in ray.nodes() if n.get("Alive")}
