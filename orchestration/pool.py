"""Ray start-up, the self-play layout (how many actors, threads and episodes each), and a pool of
self-play actors with exactly one batch in flight per actor, shared by the trainer and the bench."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import ray
from ray.exceptions import GetTimeoutError, RayActorError

from actors.selfplay import PlaySpec, PlayStats, SelfPlayActor, TaskSpec, actor_env
from rllock.config import MCTSConfig, NetConfig, SelfPlayConfig
from rllock.core.tasks import TaskSet
from rllock.errors import RLLockError

log = logging.getLogger(__name__)

PLACEMENT_TIMEOUT_S = 300.0


def largest_node_cpus() -> float:
    return max((n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n.get("Alive")), default=1.0)


class _DropDefaultTokenNotice(logging.Filter):
    """Drops Ray's notice that a new local instance uses token authentication: Ray's default, the safe
    choice, and nothing to act on. Ray's other authentication warnings (such as a cluster joined without
    it) pass."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Token authentication is enabled for this Ray cluster")


_TOKEN_LOGGER = "ray._private.authentication.authentication_token_setup"


def start_ray(address: str | None) -> bool:
    """Connect to Ray; True when this process started the instance (and so must shut it down). Ray
    starts its processes with fork(), so call this before JAX starts its threads (the first JAX array)."""
    if ray.is_initialized():
        return False
    if address:
        ray.init(address=address, logging_level=logging.WARNING)
    else:
        notices = logging.getLogger(_TOKEN_LOGGER)
        if not any(isinstance(f, _DropDefaultTokenNotice) for f in notices.filters):
            notices.addFilter(_DropDefaultTokenNotice())
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, logging_level=logging.WARNING)
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
    share = free / actors  # fractional when there are more actors than cores: they take turns
    threads = max(1, int(share))
    return Layout(actors, selfplay.episodes_per_batch, share, threads, threads, 0.0, mode)


class ActorPool:
    """Self-play actors, each with one batch in flight. A dead actor process is restarted by Ray and its
    call retried; the pool notices the new process and logs it. An actor that fails for good is dropped.

    What an actor plays (the spec and the replay buffer's handle) is put in Ray's object store once and
    travels by reference with every call, not in the constructor: Ray does not keep an actor's
    constructor arguments alive for its restarts (ray-project/ray#53727), while a retried call brings
    its own arguments."""

    def __init__(
        self,
        spec: TaskSpec | TaskSet,
        net: NetConfig,
        mcts: MCTSConfig,
        method: str,
        layout: Layout,
        seed: int,
        buffer,
    ):
        options = dict(
            num_cpus=layout.cpus,
            num_gpus=layout.gpus,
            max_restarts=-1,
            max_task_retries=-1,
            runtime_env={"env_vars": actor_env(layout.threads, gpu=layout.gpus > 0)},
        )
        self.setup = [ray.put((PlaySpec(spec, net, mcts, method, layout.episodes, layout.groups), buffer))]
        # mypy skips class decorators: @ray.remote made SelfPlayActor an ActorClass, which has .options.
        self.actors = [
            SelfPlayActor.options(**options).remote(seed + i)  # type: ignore[attr-defined]
            for i in range(layout.actors)
        ]
        try:
            pids = ray.get([a.pid.remote() for a in self.actors], timeout=PLACEMENT_TIMEOUT_S)
        except GetTimeoutError:
            raise RLLockError(
                f"the self-play actors could not start within {PLACEMENT_TIMEOUT_S:.0f} s: does a node "
                f"of the cluster have {layout.cpus:g} free CPUs{' and a GPU' if layout.gpus else ''}? "
                f"(see --actors, --evaluation)"
            ) from None
        self.pids = dict(zip(self.actors, pids))
        self.inflight: dict = {}

    def submit(self, actor, weights: list, version: int) -> None:
        self.inflight[actor.run.remote(self.setup, weights, version)] = (actor, version)

    def submit_all(self, weights: list, version: int) -> None:
        for actor in self.actors:
            self.submit(actor, weights, version)

    def oldest_version(self) -> int | None:
        return min((v for _, v in self.inflight.values()), default=None)

    def collect(self, timeout: float) -> list[tuple[object, PlayStats]]:
        """The batches finished within `timeout` seconds (at most one wait), with their actors."""
        ready, _ = ray.wait(list(self.inflight), num_returns=1, timeout=timeout)
        done = []
        for ref in ready:
            actor, _ = self.inflight.pop(ref)
            try:
                stats = ray.get(ref)
            except RayActorError as exc:  # restarts exhausted or the node is gone: go on without it
                log.error("a self-play actor failed for good: %s", str(exc).splitlines()[0])
                continue
            if self.pids[actor] != stats.pid:
                log.warning("self-play actor restarted (pid %d -> %d)", self.pids[actor], stats.pid)
                self.pids[actor] = stats.pid
            done.append((actor, stats))
        return done

    def alive(self) -> bool:
        return bool(self.inflight)

    def shutdown(self, settle_s: float = 10.0) -> None:
        """Stop every actor now; batches in flight are dropped. They are cancelled before their actors
        are killed: otherwise Ray counts each as a failed call to retry, and logs it."""
        calls = list(self.inflight)
        for ref in calls:
            ray.cancel(ref)
        for actor in self.actors:
            ray.kill(actor)
        # ray.kill returns before the actors are gone: wait for the cancelled calls to end, so that a
        # ray.shutdown right after does not race their endings.
        if calls:
            ray.wait(calls, num_returns=len(calls), timeout=settle_s)
        self.inflight.clear()
