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
    """Share of the raw chunks drawn by the closed proposal (`compiled_proposals`), which grows chunks
    that slide out along one direction, so that big pieces are removable; the rest grow uniformly from
    the frontier. None: by piece size n, 0 below `closed_from`, 1/2 up to `closed_only_from`, then 1:
    big pieces grown from the frontier are rarely removable, small ones grow faster that way."""
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
    `env.tightest_subset`), and restarts are longer. It paid at every K tried, so it is the default from
    K = 2; the former default (30) is kept by the bit-for-bit test of the plain search."""
    deep_restart_per_piece: int = 16
    """`restart_per_piece` in deep mode."""
    remainder: Literal["surface", "cut"] | None = None
    """Deep mode's judgement of a child's remainder: "surface" keeps the accepted chunks after which the
    remaining volume's surface grows least (the chunk's cut to the rest, less its faces to placed pieces
    and the outside: a chunk that takes a strand or a corner away is preferred, since a strand left to
    the end is what no last piece can lock); "cut" those with the smallest cut alone. None: by removal
    mode, "surface" under straight removal, "cut" under path removal, each the better one there."""
    child_order: Literal["count", "remainder"] | None = None
    """The order a node's children are tried in, under lookahead: "remainder", in deep mode the order of
    `remainder`'s judgement (the least growth first); "count", the most accepted continuations first.
    Either way children with no continuation are dropped. None: by removal mode, "remainder" under
    straight removal, "count" under path removal, each the better one there."""
    order_within: int = 64
    """`child_order` "remainder" orders the children of nodes with at most this many pieces left to
    place; above, the count orders them: the remainder's order pays in the last pieces, where searches
    fail, and costs too much time per node on shapes of thousands of pieces."""
    lookahead: bool = True
    """Expand children as soon as their parent is, and try first the child with the most accepted
    continuations (fail-first pruning: children with none are dropped before they are entered)."""
    dives: int = 4
    """With a guide network: each restart of the diving sequence (`dive_share`) dives this many times
    from the root (the restart's own DFS, each dive stopped at the first state `Guide.horizon` pieces
    before the end), and the restart goes on from the dive state the network values best among these
    and those earlier restarts left untaken; 1 never dives, as the solver does. Tasks with at most
    `Guide.horizon` + 1 pieces have no dive state: there the guided search is the solver's."""
    dive_share: float = 0.5
    """With a guide network: the restarts that dive are a second Luby sequence beside the solver's own,
    on a generator of their own, and one begins only while the expansions of that sequence (with its
    planned budget) stay within this share of the solver sequence's (`dive_allowance`), both counted
    since the start or the last assembly. The solver's restarts are the plain solver's, bit for bit, so
    what the solver finds early the guided search finds too, within 1 + `dive_share` times its
    expansions (and the last diving restart's); 0 never dives. A guide can then cost an easy task at
    most that factor, by construction."""
    dive_share_grows_after: int = 8
    """Restart units (`restart_unit`) of the solver sequence's expansions after which the share grows
    in proportion to them: the longer the plain search fails, the more the dives get (the hard cells the
    guide is for), while the tasks the solver finds in its first few restarts keep the plain search."""

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
    """Whether `choice` is `wanted`; None chooses it under straight removal only (under path removal
    the former search did better)."""
    return task.removal == "straight" if choice is None else choice == wanted
