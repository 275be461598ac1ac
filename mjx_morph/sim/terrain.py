"""Terrain: the physical world of each task, the per-episode random terrain, its height map and the 1410-value
height-map observation. All per-episode functions are pure JAX (jit/vmap), drawn from the env's key.

Grid. Everything is indexed on MetaMorph's observation grid (spec/environments.md §4), 10 cells per metre:
cell (c, r) with column c <-> x in [-3 + c/10, -3 + (c+1)/10) (c = 30 + floor(10 x)) and row r <-> y in
[(200 - r)/10, (201 - r)/10) (r = 200 - floor(10 y), rows grow toward -y). `height(state, c, r)` is the value of
MetaMorph's height array `H` at that cell, with `H`'s padding (csr: -10 outside the corridor; obstacle: walls 4 in
a 10-cell ring around the 1000 x 400 floor, -10 beyond) and rounded to 3 decimals as MetaMorph rounds it. The
torso height and the observation read this function; the physics reads the same cells (see below), so what the
policy sees is what the robot stands on.

Physics of csr and obstacle: one height field of P x P vertices (0.1 m spacing, P from the robot set's reach, see
`patch_size`) that follows the robot: at the start of every control step it is re-centred on the torso's cell and
refilled from the height function, vertex (i, j) at the centre of cell (c0 + i, rb - j). A whole-corridor field
(1100 x 400) per env would cost 1.8 MB per env; MJX collides each geom only with the cells under it (a window set
by `geom_rbound`), so the collision cost is the same and the patch costs ~10 kB per env.

Deviations from MetaMorph (collected in the README):
- csr: one 0.1 m vertex grid for the whole corridor (MetaMorph: boxes for the flat parts and one height field per
  segment whose vertex spacing is 2L/(20L - 1), slightly over 0.1 m); step edges and the segment ends are
  0.1 m ramps between vertex values, as inside MetaMorph's segments.
- csr rugged squares: MuJoCo stores height-field row 0 at -y while `H` has row 0 at +y, so in MetaMorph the
  observed map of a rugged-square segment is the y-mirror of the simulated one. We do **not** replicate this: the
  physics is built from the observed array, so observation and terrain agree (the band layout is random and
  symmetric in distribution, so the task is the same).
- obstacle: obstacles are height-field columns rising from the floor to z = 5.1 (MetaMorph: boxes z in [1.1, 5.1],
  floating 0.1 m above the floor, a gap a 0.1 m thick limb could just slide into); their footprint is the cells of
  MetaMorph's height-array footprint (rows [r - s_y, r + s_y), cols [c - s_x, c + s_x)), computed in integers
  (MetaMorph's float rounding can move it by one cell); walls are columns to z = 3 on the observation's wall ring;
  the floor outside the walls is a -10 m gap (unreachable).
- Both: with the height field as the only ground, terrain contacts use MJX's height-field collider (4 contacts per
  geom) instead of box/plane contacts.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..unimal.morphology import Morphology

DIVS = 10                 # HFIELD.NUM_DIVS
START_COL = 30            # START_FLAT * DIVS
HALF_ROWS = 200           # TERRAIN.SIZE[1] * DIVS
GAP = -10.0               # HFIELD.GAP_DEPTH
CSR_COLS = 1100           # 2 * 55 m
OBS_COLS = 1000           # 2 * 50 m
ROWS = 400                # 2 * 20 m
WALL_CELLS = 10           # wall ring (2 * WALL_LENGTH * DIVS)
WALL_OBS = 4.0            # value of the wall ring in H (2 * wall_height)
WALL_TOP = 3.0            # physical wall top (box centre z 1, half-height 2)
OBSTACLE_OBS = 3.0        # H over an obstacle footprint (half-height 2 + floor 1)
OBSTACLE_TOP = 5.1        # physical top of an obstacle box
Z_LO, Z_HI = GAP, 5.2     # physical height-field range (data = (z - Z_LO) / (Z_HI - Z_LO))
HFIELD_BASE = 0.1

# ---- csr corridor (terrain.py of MetaMorph, csr.yaml) -----------------------------------------------------------
FLAT_HALF_LEN = np.array([1, 2, 3])                     # FLAT_LENGTH_RANGE [1, 3, 1]
HFIELD_HALF_LEN = np.array([4, 8])                      # HFIELD_LENGTH_RANGE (curve_slope, rugged_square)
STEP_HALF_LEN = np.array([12, 16])                      # STEP_LENGTH_RANGE
CURVE_HEIGHT = np.round(np.array([0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2]), 2)   # CURVE_HEIGHT_RANGE [0.6, 1.2, 0.1]
STEP_LEVELS = np.array([0.0, 0.2, 0.4, 0.6, 0.6, 0.4, 0.2, 0.0])            # per eighth of the segment
RUGGED_F = np.array([10.0, 15.0])
RUGGED_CLIP = np.array([0.2, 0.3])                      # RUGGED_SQUARE_CLIP_RANGE
FLAT, CURVE, STEPS, RUGGED = 0, 1, 2, 3
MAX_ITERS = 56            # >= (110 - 6) / 2 flat-only iterations: the loop always reaches the corridor end
MAX_RUGGED = 12           # a rugged segment takes >= 10 m with its flat piece: at most 11 fit in 104 m
MAX_BANDS = 40            # bands of >= 10 rows over 400 rows

# ---- obstacles (objects.py + placement.py of MetaMorph, obstacle.yaml) ---------------------------------------------
NUM_OBSTACLES = 50
OBSTACLE_HALF = np.round(np.arange(0.5, 1.0, 0.1), 2).tolist() + [1.0]        # sample_from_range([0.5, 1.0, 0.1])
OBSTACLE_CELLS = np.ceil(np.asarray(OBSTACLE_HALF) * DIVS).astype(np.int32)  # as MetaMorph computes it (0.7 -> 8)
PLACEMENT_BUFFER = 60     # PLACEMENT_BUFFER_LEN * DIVS * 2 columns from each end
PLACEMENT_TRIES = 10


# ---- the height-map observation grid (wrappers/hfield.py) -----------------------------------------------------------
def _non_uniform(end: int) -> np.ndarray:
    p = np.arange(0, end) / end
    p = -np.log(1 - p)
    p = p / p[-1] * end
    return np.unique(p.astype(int))


def _non_uniform_range(low: int, hi: int) -> np.ndarray:
    pts = _non_uniform(hi)
    if low > 0:
        pts = np.concatenate([np.flip(-_non_uniform(low)), pts])
    return np.unique(pts)


OBS_BEHIND, OBS_FRONT, OBS_RIGHT, OBS_LEFT = 10, 40, 40, 40   # HFIELD.OBS_SIZE [1, 4, 4, 4] m * DIVS
MASK_DC = _non_uniform_range(OBS_BEHIND, OBS_FRONT)           # 30 column offsets (along x)
MASK_DR = _non_uniform_range(OBS_LEFT, OBS_RIGHT)             # 47 row offsets
_COL, _ROW = np.meshgrid(MASK_DC, MASK_DR)                    # (47, 30): row-major flattening = MetaMorph's order
MASK_COL = _COL.reshape(-1).astype(np.float32)
MASK_ROW = _ROW.reshape(-1).astype(np.float32)
HFIELD_OBS_SIZE = MASK_COL.size                               # 1410


class NoTerrain(NamedTuple):
    """ft and incline: nothing random per episode."""


class Corridor(NamedTuple):
    """One csr corridor as a list of contiguous segments over columns 0..1099 (segment k covers
    [seg_end[k-1], seg_end[k]), seg_end[-1] = 0; empty segments are skipped attempts) and, per rugged segment,
    its bands of rows."""
    seg_end: jax.Array     # (1 + 2 * MAX_ITERS,) int32
    seg_kind: jax.Array    # FLAT / CURVE / STEPS / RUGGED
    seg_height: jax.Array  # float32 curve height c (curve_slope)
    seg_rug: jax.Array     # int32 index of the segment's bands (rugged_square)
    band_end: jax.Array    # (MAX_RUGGED, MAX_BANDS) int32 cumulative band widths (10-19 rows each)
    band_f: jax.Array      # (MAX_RUGGED, MAX_BANDS) float32 frequency 10 or 15
    band_clip: jax.Array   # (MAX_RUGGED, MAX_BANDS) float32 clip 0.2 or 0.3


class Obstacles(NamedTuple):
    """The placed obstacles: centre on the 400 x 1000 placement grid (row grows with +y) and half-size in cells."""
    col: jax.Array         # (50,) int32
    row: jax.Array         # (50,) int32
    sx: jax.Array          # (50,) int32 ceil(10 * half-length along x)
    sy: jax.Array          # (50,) int32
    valid: jax.Array       # (50,) bool, False = no free place found in 10 tries


def cell_of(x: jax.Array, y: jax.Array) -> tuple[jax.Array, jax.Array]:
    """MetaMorph's `pos_to_idx` in unpadded cell coordinates."""
    return (START_COL + jnp.floor(x * DIVS)).astype(jnp.int32), (HALF_ROWS - jnp.floor(y * DIVS)).astype(jnp.int32)


# ---- csr ------------------------------------------------------------------------------------------------------------
def generate_corridor(key: jax.Array) -> Corridor:
    """A new random corridor (spec §3.3): after the 6 m start, repeat {flat piece of 2-6 m (truncated at the end),
    then a curve_slope / steps / rugged_square segment, skipped if it would overrun} until 110 m are covered."""
    k_loop, k_rug = jax.random.split(key)

    def body(carry, k):
        end, nrug = carry
        kt, kf, kh, kc = jax.random.split(k, 4)
        active = end < CSR_COLS
        typ = jax.random.choice(kt, jnp.array([CURVE, RUGGED, STEPS]))
        flat = jax.random.choice(kf, jnp.asarray(FLAT_HALF_LEN)) * 2 * DIVS
        flat = jnp.where(active, jnp.minimum(flat, CSR_COLS - end), 0)
        end1 = end + flat
        half = jnp.where(typ == STEPS, jax.random.choice(kh, jnp.asarray(STEP_HALF_LEN)),
                         jax.random.choice(kh, jnp.asarray(HFIELD_HALF_LEN)))
        ncol = half * 2 * DIVS
        ok = active & (end1 + ncol <= CSR_COLS)
        end2 = end1 + jnp.where(ok, ncol, 0)
        height = jax.random.choice(kc, jnp.asarray(CURVE_HEIGHT, jnp.float32))
        rug = jnp.minimum(nrug, MAX_RUGGED - 1)
        seg = (jnp.stack([end1, end2]), jnp.stack([FLAT, typ]), jnp.stack([0.0, height]), jnp.stack([0, rug]))
        return (end2, nrug + (ok & (typ == RUGGED))), seg

    keys = jax.random.split(k_loop, MAX_ITERS)
    _, (end, kind, height, rug) = jax.lax.scan(body, (jnp.int32(2 * START_COL), jnp.int32(0)), keys)
    cat = lambda first, x: jnp.concatenate([jnp.asarray([first], x.dtype), x.reshape(-1)])
    kw, kf, kc = jax.random.split(k_rug, 3)
    widths = jax.random.randint(kw, (MAX_RUGGED, MAX_BANDS), 10, 20)
    return Corridor(seg_end=cat(2 * START_COL, end).astype(jnp.int32), seg_kind=cat(FLAT, kind).astype(jnp.int32),
                    seg_height=cat(0.0, height).astype(jnp.float32), seg_rug=cat(0, rug).astype(jnp.int32),
                    band_end=jnp.cumsum(widths, axis=1).astype(jnp.int32),
                    band_f=jax.random.choice(kf, jnp.asarray(RUGGED_F, jnp.float32), (MAX_RUGGED, MAX_BANDS)),
                    band_clip=jax.random.choice(kc, jnp.asarray(RUGGED_CLIP, jnp.float32), (MAX_RUGGED, MAX_BANDS)))


def _sawtooth_half(t: jax.Array) -> jax.Array:
    """scipy.signal.sawtooth(t, width=0.5): -1 at 0, +1 at pi, -1 at 2 pi."""
    t = jnp.mod(t, 2 * jnp.pi)
    return jnp.where(t < jnp.pi, -1.0 + 2.0 * t / jnp.pi, 3.0 - 2.0 * t / jnp.pi)


def corridor_profile(tc: Corridor, c: jax.Array, r: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(inside, 1 + p) at cells (c, r), unrounded. Column j of an n-column segment has u = j / (n - 1)
    (np.linspace(0, 1, n)); curve p = c sin(pi u); steps: levels 0 .2 .4 .6 .6 .4 .2 0 by eighths;
    rugged: p = min(1 + sawtooth(f pi u, 0.5), clip) with the band of row r."""
    inside = (c >= 0) & (c < CSR_COLS) & (r >= 0) & (r < ROWS)
    cc = jnp.clip(c, 0, CSR_COLS - 1)
    rr = jnp.clip(r, 0, ROWS - 1)
    s = jnp.sum(tc.seg_end <= cc[..., None], axis=-1)            # segments are contiguous and ordered
    s = jnp.minimum(s, tc.seg_end.shape[0] - 1)
    start = jnp.where(s > 0, tc.seg_end[jnp.maximum(s - 1, 0)], 0)
    n = tc.seg_end[s] - start
    j = cc - start
    u = j.astype(jnp.float32) / jnp.maximum(n - 1, 1).astype(jnp.float32)
    kind = tc.seg_kind[s]
    curve = tc.seg_height[s] * jnp.sin(jnp.pi * u)
    steps = jnp.asarray(STEP_LEVELS, jnp.float32)[jnp.clip(j * 8 // jnp.maximum(n, 1), 0, 7)]
    rug = tc.seg_rug[s]
    band = jnp.minimum(jnp.sum(tc.band_end[rug] <= rr[..., None], axis=-1), MAX_BANDS - 1)
    f, clip = tc.band_f[rug, band], tc.band_clip[rug, band]
    rugged = jnp.minimum(1.0 + _sawtooth_half(f * jnp.pi * u), clip)
    p = jnp.where(kind == CURVE, curve, jnp.where(kind == STEPS, steps, jnp.where(kind == RUGGED, rugged, 0.0)))
    return inside, 1.0 + p


# ---- obstacles ------------------------------------------------------------------------------------------------------
def generate_obstacles(key: jax.Array) -> Obstacles:
    """50 attempts to place a box of half-lengths in {0.5, ..., 1.0} m, each with up to 10 uniform draws of its
    centre on the 400 x 1000 placement grid, rejected if its footprint overlaps an earlier box (touching allowed)."""
    sizes = jnp.asarray(OBSTACLE_CELLS)

    def body(placed, k):
        kx, ky, kr, kc = jax.random.split(k, 4)
        sx = jax.random.choice(kx, sizes)
        sy = jax.random.choice(ky, sizes)
        row = jax.random.randint(kr, (PLACEMENT_TRIES,), sy, ROWS - sy)
        col = jax.random.randint(kc, (PLACEMENT_TRIES,), sx + PLACEMENT_BUFFER, OBS_COLS - sx - PLACEMENT_BUFFER)
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


def _in_any_box(to: Obstacles, c: jax.Array, r: jax.Array) -> jax.Array:
    """Cell (c, r) in MetaMorph's H footprint of an obstacle: cols [col - sx, col + sx), rows [R - sy, R + sy)
    with R = 400 - row the H row of the centre (placement rows grow with +y, H rows with -y)."""
    cs, rs = c[..., None], r[..., None]
    rh = ROWS - to.row
    return (to.valid & (cs >= to.col - to.sx) & (cs < to.col + to.sx) & (rs >= rh - to.sy)
            & (rs < rh + to.sy)).any(axis=-1)


NEAR_BOXES = 16           # obstacles considered around the torso (patch and observation reach <= 57 cells)
NEAR_CELLS = 60


def near_obstacles(to: Obstacles, ct: jax.Array, rt: jax.Array, k: int = NEAR_BOXES) -> Obstacles:
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


def _local(kind: str, ts, ct, rt):
    return near_obstacles(ts, ct, rt) if kind == "obstacles" else ts


# ---- one interface for the tasks ------------------------------------------------------------------------------------
def generate(kind: str, key: jax.Array):
    if kind == "corridor":
        return generate_corridor(key)
    if kind == "obstacles":
        return generate_obstacles(key)
    return NoTerrain()


def height(kind: str, ts, c: jax.Array, r: jax.Array) -> jax.Array:
    """MetaMorph's height array H at cells (c, r) (padding included, rounded to 3 decimals)."""
    if kind == "corridor":
        inside, h = corridor_profile(ts, c, r)
        h = jnp.where(inside, h, GAP)
    elif kind == "obstacles":
        floor = (c >= 0) & (c < OBS_COLS) & (r >= 0) & (r < ROWS)
        ring = (c >= -WALL_CELLS) & (c < OBS_COLS + WALL_CELLS) & (r >= -WALL_CELLS) & (r < ROWS + WALL_CELLS)
        h = jnp.where(floor, 1.0, jnp.where(ring, WALL_OBS, GAP))
        h = jnp.where(_in_any_box(ts, c, r), OBSTACLE_OBS, h)
    else:
        raise ValueError(kind)
    return jnp.round(h.astype(jnp.float32), 3)


def physical_height(kind: str, ts, c: jax.Array, r: jax.Array) -> jax.Array:
    """Surface z of the physics at the centre of cell (c, r)."""
    if kind == "corridor":
        inside, h = corridor_profile(ts, c, r)
        return jnp.where(inside, h, GAP)
    floor = (c >= 0) & (c < OBS_COLS) & (r >= 0) & (r < ROWS)
    ring = (c >= -WALL_CELLS) & (c < OBS_COLS + WALL_CELLS) & (r >= -WALL_CELLS) & (r < ROWS + WALL_CELLS)
    h = jnp.where(floor, 1.0, jnp.where(ring, WALL_TOP, GAP))
    return jnp.where(_in_any_box(ts, c, r), OBSTACLE_TOP, h)


# ---- the physical height-field patch --------------------------------------------------------------------------------
def patch_size(robots: list[Morphology] | tuple[Morphology, ...], motion: float = 0.5) -> int:
    """Odd number of vertices per side of the moving height field: the largest distance any point of any robot
    can reach from its torso centre (chain of body offsets, joint offsets and capsules), plus `motion` for the
    control step's movement and the collision window."""
    reach = 0.0
    for m in robots:
        origin = []      # bound on the distance of each limb's body origin from the torso centre
        for l in m.limbs:
            base = 0.0 if l.parent < 0 else origin[l.parent]
            jpos = max((float(np.linalg.norm(j.pos)) for j in l.joints), default=0.0)
            origin.append(base + float(np.linalg.norm(l.pos)) + 2 * jpos)
            reach = max(reach, origin[-1] + l.length + l.radius)
    half = int(np.ceil((reach + motion) * DIVS))
    return 2 * half + 1


def hfield_world_xml(p: int) -> tuple[str, str]:
    """(asset, geom) MJCF of the patch: P x P vertices 0.1 m apart, z from Z_LO (data 0) to Z_HI (data 1)."""
    half = (p - 1) / 2 / DIVS
    asset = (f'    <hfield name="terrain" nrow="{p}" ncol="{p}" '
             f'size="{half:g} {half:g} {Z_HI - Z_LO:g} {HFIELD_BASE:g}"/>')
    geom = (f'    <geom name="terrain" type="hfield" hfield="terrain" pos="0 0 {Z_LO:g}" '
            f'contype="0" conaffinity="1"/>')
    return asset, geom


def patch(kind: str, ts, x: jax.Array, y: jax.Array, p: int) -> tuple[jax.Array, jax.Array]:
    """Height-field data (P*P,) and geom position (3,) of the patch centred on the cell of (x, y)."""
    ct, rt = cell_of(x, y)
    ts = _local(kind, ts, ct, rt)
    h = (p - 1) // 2
    i = jnp.arange(p)
    c = ct - h + i                     # vertex column i  -> cell column
    r = rt + h - i                     # vertex row j     -> cell row (row j grows toward +y, cell rows toward -y)
    z = physical_height(kind, ts, c[None, :], r[:, None])         # (row j, column i)
    data = jnp.clip((z - Z_LO) / (Z_HI - Z_LO), 0.0, 1.0).reshape(-1)
    cx = -3.0 + ct.astype(jnp.float32) / DIVS + 0.5 / DIVS
    cy = (HALF_ROWS - rt).astype(jnp.float32) / DIVS + 0.5 / DIVS
    return data.astype(jnp.float32), jnp.stack([cx, cy, jnp.float32(Z_LO)])


# ---- observation ----------------------------------------------------------------------------------------------------
def hfield_obs(kind: str, ts, x: jax.Array, y: jax.Array, yaw: jax.Array) -> jax.Array:
    """The 1410 height-map values relative to the ground under the torso, grid rotated by the torso yaw."""
    ct, rt = cell_of(x, y)
    ts = _local(kind, ts, ct, rt)
    cos, sin = jnp.cos(yaw), jnp.sin(yaw)
    dc = jnp.round(cos * MASK_COL + sin * MASK_ROW).astype(jnp.int32)
    dr = jnp.round(-sin * MASK_COL + cos * MASK_ROW).astype(jnp.int32)
    return height(kind, ts, ct + dc, rt + dr) - height(kind, ts, ct, rt)


def ground_height(task, ts, x: jax.Array, y: jax.Array) -> jax.Array:
    """Ground z used for the torso height (MetaMorph's UnimalHeightObs)."""
    if task.terrain == "plane":
        return jnp.float32(1.0)
    if task.terrain == "incline":
        # H = 1 + tan(a) (col/10 - 75) over the 1500 slab columns, -10 padding beyond; not clipped at 0
        col = jnp.floor(x * DIVS)
        h = 1.0 + np.tan(np.radians(task.incline_deg)) * col / DIVS
        h = jnp.round(h, 3)
        return jnp.where((col >= -750) & (col < 750), h, GAP)
    ct, rt = cell_of(x, y)
    return jnp.maximum(height(task.terrain, _local(task.terrain, ts, ct, rt), ct, rt), 0.0)
