"""The search's configuration: how many chunks a node samples and keeps, in what order it tries them,
how long its restarts run, and how a guide network's dives share the search. One frozen dataclass, so a
configuration is a value that runs, tests and benches pass around and compare."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from rllock.core.env import Task


@dataclass(frozen=True)
class SearchConfig:
    samples_per_node: int = 512
    """Raw chunks sampled when a node is expanded."""
    children: int = 8
    """Distinct accepted chunks kept per node (which, and in what order they are tried: `remainder`,
    `child_order`)."""
    restart_base: int = 64
    """Node expansions per unit of the Luby restart schedule (at least)."""
    restart_per_piece: int = 4
    """The Luby unit is at least this many expansions per piece to place (`deep_restart_per_piece` in
    deep mode): a deep search needs hundreds of expansions only to walk down once with lookahead."""
    closed_share: float | None = None
    """Share of the raw chunks drawn by the closed proposal (`compiled_sampler`), which grows chunks
    that slide out along one direction, so that big pieces are removable; the rest grow uniformly from
    the frontier. None: by piece size n, 0 below `closed_from`, 1/2 up to `closed_only_from`, then 1.
    Measured (seed 0, one core): frontier growth alone finds nothing on desia-bunny K=10-30 (n >= 32)
    and is faster on 5^3-6^3 cubes (n = 9-10); in between, half of each did best (desia-bunny K=40/60,
    mario K=30, desia-dog K=40)."""
    closed_from: int = 12
    """The piece size n from which `closed_share=None` draws closed-proposal chunks."""
    closed_only_from: int = 32
    """The piece size n from which `closed_share=None` draws closed-proposal chunks only."""
    deep_from: int = 2
    """From this K on, the search runs in deep mode, which keeps the remaining volume compact: pieces
    fail late, when what remains of R has become thin strands that no piece can be cut from without
    cutting R apart. In deep mode a chunk may start at any R voxel that touches a placed piece (not only
    the previous piece: stragglers get picked up), frontier growth takes the thinner of two frontier
    voxels, a node's children are its accepted chunks that leave R most compact (`remainder`,
    `env.tightest_subset`), and restarts are longer. Measured first on desia-dog K=60 (seed 0, one
    core): the default search reached 55 of 59 pieces in 300 s; the smallest cuts, 55; with wide seeds,
    57; with thin growth too, 58 in 240 s; with longer restarts too, all 59 in 111 s. It was the mode
    from K = 30 on until it was measured at small K too (docs/benchmarks.md, "Deep mode at every K"):
    seconds to the first assembly, seeds 0-2, fell on every cell tried (cube6 K=25 2.7-31 s to
    0.3-1.1 s, cube4 K=9 none in 60 s to 1.5-3.2 s) and sofa K=19, which no search of the solver had
    solved, was solved in 37-149 s. So it is the default at every K; `deep_from` stays to compare."""
    deep_restart_per_piece: int = 16
    """`restart_per_piece` in deep mode."""
    remainder: Literal["surface", "cut"] | None = None
    """Deep mode's judgement of a child's remainder: "surface" keeps the accepted chunks after which the
    remaining volume's surface grows least (the chunk's cut to the rest, less its faces to placed pieces
    and the outside: a chunk that takes a strand or a corner away is preferred, since a strand left to
    the end is what no last piece can lock); "cut" those with the smallest cut alone. None: by removal
    mode, "surface" under straight removal (sofa K=19 median 5.7 s to the first assembly against 60 s
    unsolved, cube4 K=9 0.1 s against 3.3 s), "cut" under path removal (desia-bunny K=80, seeds 0-5,
    120 s: cut solved 4, surface 2). Measured side by side (docs/benchmarks.md, "The remainder's
    surface")."""
    child_order: Literal["count", "remainder"] | None = None
    """The order a node's children are tried in, under lookahead: "remainder", in deep mode the order of
    `remainder`'s judgement (the least growth first); "count", the most accepted continuations first
    (the only order until the commit after 24493fb). Either way children with no continuation are
    dropped. None: by removal mode, "remainder" under straight removal, "count" under path removal.
    Rollouts from a node's kept children (`scripts/chunk_study.py`) ordered 61.8% of their sibling pairs
    rightly by the remainder's surface and 39.1% by the count (174 pairs); in the search, seeds 0-4,
    60 s, desia-dog K=60 was solved on 5 seeds against 2 and sofa K=19's median fell from 4.3 to 1.8 s;
    desia-bunny K=80 path, seeds 0-5, 120 s, was solved on 2 seeds against 4 (docs/benchmarks.md,
    "Which chunks become children, and in what order they are tried")."""
    order_within: int = 64
    """`child_order` "remainder" orders the children of nodes with at most this many pieces left to
    place; above, the count orders them. On the Stanford bunny at resolution 30 with K = 300 the
    remainder's order at every node took 292 s against the count's 19 s (seed 0); with it in the last 16
    pieces only, desia-dog K=60 lost most of its gain (seeds 0-2: none, 54.7, 0.7 s against 2.9, 6.9,
    8.6 s); in the last 64, the bunny took 20.7 and 20.1 s (seeds 0, 1; the count 19.1 and 22.1 s)."""
    lookahead: bool = True
    """Expand children as soon as their parent is, and try first the child with the most accepted
    continuations (fail-first pruning: children with none are dropped before they are entered)."""
    dives: int = 4
    """With a guide network: each restart of the diving sequence (`dive_share`) dives this many times
    from the root (the restart's own DFS, each dive stopped at the first state `Guide.horizon` pieces
    before the end), and the restart goes on from the dive state the network values best among these
    and those earlier restarts left untaken; 1 never dives, as the solver does. With 4, a guide taught
    mario solved mario K=60 on 12 seeds of 18 in 300 s, the untrained network on 4 and the solver on 2
    of 9; two more trainings of the same command, 2 of 8 and 3 of 17 (docs/benchmarks.md, "mario K=60
    on 18 seeds", "Which search the actors run").
    Tasks with at most `Guide.horizon` + 1 pieces have no dive state: there the guided search is the
    solver's."""
    dive_share: float = 0.5
    """With a guide network: the restarts that dive are a second Luby sequence beside the solver's own,
    on a generator of their own, and one begins only while the expansions of that sequence (with its
    planned budget) stay within this share of the solver sequence's (`dive_allowance`), both counted
    since the start or the last assembly. The solver's restarts are the plain solver's, bit for bit, so
    what the solver finds early the guided search finds too, within 1 + `dive_share` times its
    expansions (and the last diving restart's); 0 never dives. Before, every restart from the second
    dived, which cost easy cells up to 14x (the beetle mesh; docs/benchmarks.md, "The guide beside the
    solver"). Shares 1.0 and 2.0 solved mario K=60 on 7 seeds of 16 within 150 s where 0.5 solved 5,
    but single seeds of cells the solver solves within a minute took up to 2.2x its time: 0.5 keeps the
    bound of 1.5x by construction ("How much of the search the dives get")."""
    dive_share_grows_after: int = 8
    """Restart units (`restart_unit`) of the solver sequence's expansions after which the share grows
    in proportion to them: the longer the plain search fails, the more the dives get (the hard cells the
    guide is for). 8 units are the solver's first 6 restarts; it found the easy cells (under 5 s:
    desia-dog K=60, the beetle mesh at 24 with K=61, mario K=58 on 5 seeds of 6) within 0.5-6.5 units,
    and fandisk at 24 with K=174 on seed 0 in about 80 (docs/benchmarks.md, "The guide beside the
    solver")."""

    def share_for(self, task: Task) -> float:
        """The share of closed-proposal chunks for `task`."""
        if self.closed_share is not None:
            return self.closed_share
        n = task.piece_size
        return 1.0 if n >= self.closed_only_from else 0.5 if n >= self.closed_from else 0.0

    def deep(self, task: Task) -> bool:
        return task.pieces >= self.deep_from

    def by_remainder(self, task: Task, left: int) -> bool:
        """Whether a node with `left` pieces left to place tries its children in the order of the
        remainder's judgement (`child_order`, `order_within`): only in deep mode, where
        `env.tightest_subset` hands them over in that order."""
        return self.deep(task) and left <= self.order_within and _chosen(self.child_order, "remainder", task)

    def surface(self, task: Task) -> bool:
        """Whether deep mode keeps the children that grow the remainder's surface least (`remainder`)."""
        return _chosen(self.remainder, "surface", task)

    def restart_unit(self, task: Task, placed: int) -> int:
        """Node expansions per unit of the Luby schedule for a search of `task` to `placed` pieces."""
        per_piece = self.deep_restart_per_piece if self.deep(task) else self.restart_per_piece
        return max(self.restart_base, per_piece * placed)


def _chosen(choice: str | None, wanted: str, task: Task) -> bool:
    """Whether `choice` is `wanted`; None chooses it under straight removal only, where it was measured
    better (under path removal the former search is kept)."""
    return task.removal == "straight" if choice is None else choice == wanted
