"""The shared tree (supertree) of a robot set: one kinematic tree into which every robot of the set embeds.

MJX keeps the kinematic tree static, so robots of different topologies can only share one compiled step if they
share one tree. A robot embeds into the shared tree by an injective map limb -> slot that preserves parents (a limb
on the torso goes to a child slot of the torso slot, a limb on limb j goes to a child slot of j's slot).

Construction: start from one robot's tree and merge the robots in one at a time. Merging matches the children of
two nodes by a maximum-weight bipartite matching whose weight is the size of the largest common subtree of the two
children (computed recursively, so the match is optimal for that pair of trees); matched children are merged
recursively and unmatched robot children become new slots. Greedy merging depends on the order, so a few orders
(largest robots first, then seeded shuffles) are tried and the smallest tree kept. The tree sizes of the robot sets
are in `docs/benchmarks.md`.

Slots are numbered in depth-first pre-order of the shared tree (slot 0 = torso), which is also the MuJoCo body
order of every padded robot (body id = slot + 1; body 0 is the world). Children of a node are ordered by how many
robots use them (most used first), so the layout is deterministic for a given set.
"""
from __future__ import annotations

import dataclasses
import random
from functools import lru_cache, partial
from typing import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..unimal.morphology import TORSO, Morphology
from . import processes

PARALLEL_FROM_ROBOTS = 500     # robots from which the merge orders run in processes (below, a process costs more)

# A rooted unordered tree as nested tuples of children: () is a leaf. Used for the common-subtree recursion.
_Shape = tuple


def _robot_shape(m: Morphology, index: int = TORSO) -> _Shape:
    return tuple(sorted(_robot_shape(m, c) for c in m.children(index)))


@lru_cache(maxsize=None)
def _common(a: _Shape, b: _Shape) -> int:
    """Number of nodes of the largest common rooted subtree of a and b (roots matched to each other)."""
    if not a or not b:
        return 1
    w = np.array([[_common(x, y) for y in b] for x in a], dtype=float)
    rows, cols = linear_sum_assignment(w, maximize=True)
    return 1 + int(w[rows, cols].sum())


@dataclasses.dataclass
class _Node:
    children: list["_Node"]
    users: int = 0
    id: int = -1

    def shape(self) -> _Shape:
        return tuple(sorted(c.shape() for c in self.children))


def _merge(node: _Node, m: Morphology, index: int, out: dict[int, _Node]) -> None:
    """Embed the robot subtree rooted at `index` (TORSO or a limb) onto `node`, growing the tree where needed.
    `out` receives limb index -> node."""
    node.users += 1
    kids = m.children(index)
    if not kids:
        return
    if node.children:
        ks = [_robot_shape(m, k) for k in kids]
        ns = [c.shape() for c in node.children]
        w = np.array([[_common(a, b) for b in ns] for a in ks], dtype=float)
        rows, cols = linear_sum_assignment(w, maximize=True)
        match = dict(zip(rows.tolist(), cols.tolist()))
    else:
        match = {}
    for i, k in enumerate(kids):
        if i in match:
            child = node.children[match[i]]
        else:
            child = _Node(children=[])
            node.children.append(child)
        out[k] = child
        _merge(child, m, k, out)


@dataclasses.dataclass(frozen=True)
class SharedTree:
    """A shared tree and the embedding of each robot of its set.

    parent[s]     parent slot of slot s (-1 for the torso slot 0); parent[s] < s.
    users[s]      how many robots of the set use slot s.
    slot_of[r][i] slot of limb i (MuJoCo body order of robot r's own file) of robot r.
    """
    parent: tuple[int, ...]
    users: tuple[int, ...]
    slot_of: tuple[tuple[int, ...], ...]
    names: tuple[str, ...]

    @property
    def num_slots(self) -> int:
        """Bodies of a padded robot, torso included (the world body not counted)."""
        return len(self.parent)

    @property
    def num_limb_slots(self) -> int:
        return len(self.parent) - 1

    def children(self, slot: int) -> list[int]:
        return [s for s, p in enumerate(self.parent) if p == slot]

    def depth(self, slot: int) -> int:
        d = 0
        while slot > 0:
            slot = self.parent[slot]
            d += 1
        return d

    def check(self, robots: Sequence[Morphology]) -> None:
        """Raise if an embedding is not a parent-preserving injection (a bug, never a user error)."""
        for m, slots in zip(robots, self.slot_of):
            if len(set(slots)) != len(slots) or 0 in slots:
                raise AssertionError(f"{m.name}: embedding is not injective: {slots}")
            for i, l in enumerate(m.limbs):
                want = 0 if l.parent == TORSO else slots[l.parent]
                if self.parent[slots[i]] != want:
                    raise AssertionError(f"{m.name}: limb {i} in slot {slots[i]} whose parent is not {want}")


def _build_once(robots: Sequence[Morphology], order: Sequence[int]) -> SharedTree:
    root = _Node(children=[])
    maps: dict[int, dict[int, _Node]] = {}
    for r in order:
        out: dict[int, _Node] = {}
        _merge(root, robots[r], TORSO, out)
        maps[r] = out
    # number the nodes depth-first, most-used children first (stable in insertion order otherwise)
    parents: list[int] = []
    users: list[int] = []

    def visit(node: _Node, parent: int) -> None:
        node.id = len(parents)
        parents.append(parent)
        users.append(node.users)
        for c in sorted(node.children, key=lambda c: -c.users):
            visit(c, node.id)

    visit(root, -1)
    slot_of = tuple(tuple(maps[r][i].id for i in range(robots[r].num_limbs)) for r in range(len(robots)))
    return SharedTree(parent=tuple(parents), users=tuple(users), slot_of=slot_of,
                      names=tuple(m.name for m in robots))


def build_shared_tree(robots: Sequence[Morphology], tries: int = 16, seed: int = 0) -> SharedTree:
    """The smallest shared tree found over `tries` merge orders (largest robots first, then seeded shuffles)."""
    robots = list(robots)
    if not robots:
        raise ValueError("build_shared_tree: empty robot set")
    n = len(robots)
    by_size = sorted(range(n), key=lambda i: (-robots[i].num_limbs, -robots[i].tree_depth, i))
    orders = [by_size, list(range(n))]
    rng = random.Random(seed)
    for _ in range(max(0, tries - len(orders))):
        o = list(range(n))
        rng.shuffle(o)
        orders.append(o)
    orders = orders[:max(1, tries)]
    # each order on its own core for a large set (the 2400 variants: ~0.5 s an order); the first smallest is kept
    n = processes.processes_for(len(orders), 1) if len(robots) >= PARALLEL_FROM_ROBOTS else 1
    trees = processes.process_map(partial(_build_once, robots), orders, n, "the shared tree's merge orders")
    best = min(trees, key=lambda t: t.num_slots)
    best.check(robots)
    return best
