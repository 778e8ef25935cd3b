"""Chains of lanes through a prepared lane graph (:mod:`ctgpp.data.lane_index`): the paths ahead
through successors, the straightest chain through a lane, and points at fixed spacing along chains.

Only the walk through the lane graph (a few lane ids per chain) is Python; the resampling of all
chains is one vectorized lookup by arc length (:meth:`~ctgpp.data.lane_index.LaneIndex.at`).
"""

from __future__ import annotations

import itertools

import numpy as np

from ctgpp.data.lane_index import LaneIndex


def paths_ahead(index: LaneIndex, lane: int, reach_m: float, max_paths: int) -> list[list[int]]:
    """Lane chains from ``lane`` through successors until they cover ``reach_m`` from its start.

    One chain per distinct branch, at most ``max_paths``: the straightest first, then those that
    turn at fewer forks, a turn at a nearer fork before one at a farther fork (so that every branch
    of the first fork comes before the second fork's). A chain also ends where the graph does or
    would loop.
    """
    leaves: list[tuple[int, tuple[int, ...], list[int]]] = []
    stack: list[tuple[list[int], tuple[int, ...], float]] = [([lane], (), index.lengths[lane])]
    budget = 8 * max_paths + 16  # expansions: dense intersections must not blow up the search
    while stack and budget > 0:
        budget -= 1
        chain, ranks, covered = stack.pop()
        nxt = [j for j in index.successors[chain[-1]] if j not in chain] if covered < reach_m else []
        if not nxt:
            leaves.append((sum(ranks), tuple(-r for r in ranks), chain))
            continue
        fork = len(nxt) > 1
        for r in range(len(nxt) - 1, -1, -1):  # pushed in reverse: the straightest is expanded first
            j = nxt[r]
            stack.append(([*chain, j], (*ranks, r) if fork else ranks, covered + index.lengths[j]))
    leaves.extend((sum(r), tuple(-x for x in r), c) for c, r, _ in stack)  # cut short by the budget
    leaves.sort(key=lambda leaf: (leaf[0], leaf[1]))
    return [chain for _, _, chain in leaves[:max_paths]]


def straight_chain(
    index: LaneIndex,
    lane: int,
    ahead_m: float,
    behind_m: float,
    avoid: frozenset[int] | set[int] = frozenset(),
    slide: bool = False,
) -> tuple[list[int], float, float]:
    """The straightest lane chain through ``lane``: its first successor after another until they
    cover ``ahead_m`` from ``lane``'s start, its best aligned predecessors until they cover ``behind_m``
    before it (at most four), never into a lane of ``avoid`` or around a loop. With ``slide``, what
    the successors fall short of ``ahead_m`` is asked of the predecessors too.

    Returns the chain, the length (m) of the lanes prepended before ``lane`` and the shortfall ahead.
    """
    chain, lengths, succ, pred = [lane], index.lengths, index.successors, index.predecessors
    covered = lengths[lane]
    while covered < ahead_m:
        nxt = succ[chain[-1]]
        if not nxt or nxt[0] in avoid or nxt[0] in chain:
            break
        chain.append(nxt[0])
        covered += lengths[nxt[0]]
    short = max(ahead_m - covered, 0.0)
    behind_m += short if slide else 0.0
    before: list[int] = []
    prepended = 0.0
    while prepended < behind_m and len(before) < 4:
        prv = pred[before[-1] if before else lane]
        if not prv or prv[0] in avoid or prv[0] in chain or prv[0] in before:
            break
        before.append(prv[0])
        prepended += lengths[prv[0]]
    return before[::-1] + chain, prepended, short


def resample_chains(
    index: LaneIndex, chains: list[list[int]], start_m: np.ndarray, spacing_m: float, n_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points along lane chains (each lane followed by the next) at fixed spacing.

    chains: K lists of lanes; start_m (K,) arc length of the first point along its chain (m from the
    first lane's start; negative before it). Returns xy (K, P, 2) world m, direction (K, P, 2) unit,
    and valid (K, P): the point lies on the chain (between its start and its end).
    """
    size = np.fromiter(map(len, chains), dtype=np.int64, count=len(chains))  # (K,)
    flat = np.fromiter(itertools.chain.from_iterable(chains), dtype=np.int64, count=int(size.sum()))
    first = np.cumsum(size) - size  # (K,) each chain's first entry in ``flat``
    length = index.length[flat]
    end = np.cumsum(length)  # chains laid end to end: where each of their lanes ends
    base = end[first] - length[first]  # (K,) where each chain starts
    total = end[first + size - 1] - base  # (K,) chain lengths
    target = start_m[:, None] + spacing_m * np.arange(n_points)  # (K, P) along each chain
    q = base[:, None] + np.clip(target, 0.0, total[:, None])
    pos = np.searchsorted(end, q, side="right")  # (K, P) the lane entry holding each point
    pos = np.clip(pos, first[:, None], (first + size - 1)[:, None])
    xy, direction = index.at(flat[pos], q - (end[pos] - length[pos]))
    valid = (target >= -1e-6) & (target <= total[:, None] + 1e-6)
    return xy, direction, valid
