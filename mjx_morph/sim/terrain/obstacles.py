"""The obstacle task's field: a 100 m x 40 m floor with walls around it and 50 boxes placed at random per episode
(MetaMorph's objects.py + placement.py with obstacle.yaml). The boxes are drawn on MetaMorph's placement grid and
read through the cells of the height-array grid (`grid.py`); `terrain.ObstacleField` turns them into MetaMorph's
height array and the physics.

Deviations from MetaMorph (listed in `mjx_morph/sim/__init__.py`): obstacles are height-field columns rising from
the floor to z = 5.1 (MetaMorph: boxes z in [1.1, 5.1], floating 0.1 m above the floor, a gap a 0.1 m thick limb
could just slide into); their footprint is the cells of MetaMorph's height-array footprint (rows [r - s_y, r + s_y),
cols [c - s_x, c + s_x)), computed in integers (MetaMorph's float rounding can move it by one cell); walls are
columns to z = 3 on the observation's wall ring; the floor outside the walls is a -10 m gap (unreachable).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .grid import DIVS, ROWS, pick

OBS_COLS = 1000           # 2 * 50 m
WALL_CELLS = 10           # wall ring (2 * WALL_LENGTH * DIVS)
WALL_OBS = 4.0            # value of the wall ring in H (2 * wall_height)
WALL_TOP = 3.0            # physical wall top (box centre z 1, half-height 2)
OBSTACLE_OBS = 3.0        # H over an obstacle footprint (half-height 2 + floor 1)
OBSTACLE_TOP = 5.1        # physical top of an obstacle box
NUM_OBSTACLES = 50
OBSTACLE_HALF = np.round(np.arange(0.5, 1.0, 0.1), 2).tolist() + [1.0]        # sample_from_range([0.5, 1.0, 0.1])
OBSTACLE_CELLS = np.ceil(np.asarray(OBSTACLE_HALF) * DIVS).astype(np.int32)  # as MetaMorph computes it (0.7 -> 8)
PLACEMENT_BUFFER = 60     # PLACEMENT_BUFFER_LEN * DIVS * 2 columns from each end
PLACEMENT_TRIES = 10
NEAR_BOXES = 16           # obstacles considered around the torso (patch and observation reach <= 57 cells)
NEAR_CELLS = 60


class Obstacles(NamedTuple):
    """The placed obstacles: centre on the 400 x 1000 placement grid (row grows with +y) and half-size in cells."""
    col: jax.Array         # (50,) int32
    row: jax.Array         # (50,) int32
    sx: jax.Array          # (50,) int32 ceil(10 * half-length along x)
    sy: jax.Array          # (50,) int32
    valid: jax.Array       # (50,) bool, False = no free place found in 10 tries


def generate(key: jax.Array) -> Obstacles:
    """50 attempts to place a box of half-lengths in {0.5, ..., 1.0} m, each with up to 10 uniform draws of its
    centre on the 400 x 1000 placement grid, rejected if its footprint overlaps an earlier box (touching allowed)."""
    sizes = jnp.asarray(OBSTACLE_CELLS, jnp.int32)

    def body(placed, k):
        kx, ky, kr, kc = jax.random.split(k, 4)
        sx = pick(kx, sizes)
        sy = pick(ky, sizes)
        row = jax.random.randint(kr, (PLACEMENT_TRIES,), sy, ROWS - sy, jnp.int32)
        col = jax.random.randint(kc, (PLACEMENT_TRIES,), sx + PLACEMENT_BUFFER, OBS_COLS - sx - PLACEMENT_BUFFER,
                                 jnp.int32)
        pc, pr, psx, psy, pv = placed          # (50,) each; invalid ones have size 0
        overlap = ((col[:, None] - sx < pc + psx) & (pc - psx < col[:, None] + sx)
                   & (row[:, None] - sy < pr + psy) & (pr - psy < row[:, None] + sy) & pv)
        free = ~overlap.any(axis=1)
        ok = free.any()
        first = jnp.argmax(free)
        return placed, (col[first], row[first], sx, sy, ok)

    def scan_body(carry, xs):
        i, k = xs
        _, (c, r, sx, sy, ok) = body(carry, k)
        pc, pr, psx, psy, pv = carry
        carry = (pc.at[i].set(c), pr.at[i].set(r), psx.at[i].set(sx), psy.at[i].set(sy), pv.at[i].set(ok))
        return carry, None

    z = jnp.zeros((NUM_OBSTACLES,), jnp.int32)
    init = (z, z, z, z, jnp.zeros((NUM_OBSTACLES,), bool))
    (c, r, sx, sy, v), _ = jax.lax.scan(scan_body, init, (jnp.arange(NUM_OBSTACLES), jax.random.split(key, NUM_OBSTACLES)))
    return Obstacles(col=c, row=r, sx=sx, sy=sy, valid=v)


def in_any_box(to: Obstacles, c: jax.Array, r: jax.Array) -> jax.Array:
    """Cell (c, r) in MetaMorph's H footprint of an obstacle: cols [col - sx, col + sx), rows [R - sy, R + sy)
    with R = 400 - row the H row of the centre (placement rows grow with +y, H rows with -y)."""
    cs, rs = c[..., None], r[..., None]
    rh = ROWS - to.row
    return (to.valid & (cs >= to.col - to.sx) & (cs < to.col + to.sx) & (rs >= rh - to.sy)
            & (rs < rh + to.sy)).any(axis=-1)


def near(to: Obstacles, ct: jax.Array, rt: jax.Array, k: int = NEAR_BOXES) -> Obstacles:
    """The k obstacles closest to cell (ct, rt) (Chebyshev distance to the footprint, skipped ones last), with
    those farther than NEAR_CELLS dropped. The height-field patch and the height map only reach 57 cells from the
    torso; 50 obstacles of >= 1 m spread over 88 m x 40 m put ~1.6 within that reach on average, so 16 is exact
    in practice and keeps the per-step work (and XLA's compile time) small."""
    rh = ROWS - to.row
    dc = jnp.maximum(jnp.maximum((to.col - to.sx) - ct, ct - (to.col + to.sx - 1)), 0)
    dr = jnp.maximum(jnp.maximum((rh - to.sy) - rt, rt - (rh + to.sy - 1)), 0)
    dist = jnp.where(to.valid, jnp.maximum(dc, dr), 10**6)
    _, idx = jax.lax.top_k(-dist, k)
    sel = jax.tree_util.tree_map(lambda x: x[idx], to)
    return sel._replace(valid=sel.valid & (dist[idx] <= NEAR_CELLS))
