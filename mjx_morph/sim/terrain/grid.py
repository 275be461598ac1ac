"""MetaMorph's height-array grid, shared by the csr corridor and the obstacle field: cells, the moving height-field
patch the physics collides with, and the sampling grid of the 1410-value height-map observation.

Cells: 10 per metre. Cell (c, r) has column c <-> x in [-3 + c/10, -3 + (c+1)/10) (c = 30 + floor(10 x)) and row
r <-> y in [(200 - r)/10, (201 - r)/10) (r = 200 - floor(10 y), rows grow toward -y), as MetaMorph's `pos_to_idx`
(its arena starts 3 m behind the robot and is 40 m wide). A terrain's `height(state, c, r)` is the value of
MetaMorph's height array `H` at that cell, its `physical_height(state, c, r)` the surface the physics builds
there.

Patch: one height field of P x P vertices 0.1 m apart (P from the robot set's reach, `patch_size`) that follows
the robot: at the start of every control step it is re-centred on the torso's cell and refilled from the terrain's
physical height, vertex (i, j) at the centre of cell (c0 + i, rb - j). MJX collides each geom only with the cells
under it (a window set by `geom_rbound`), so a patch collides exactly like a whole-corridor field at a fraction
of its memory (docs/benchmarks.md).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...unimal.morphology import Morphology

DIVS = 10                 # HFIELD.NUM_DIVS: cells per metre
START_COL = 30            # START_FLAT * DIVS: column of x = 0
HALF_ROWS = 200           # TERRAIN.SIZE[1] * DIVS: row of y = 0
ROWS = 400                # 2 * 20 m
GAP = -10.0               # HFIELD.GAP_DEPTH: height outside the terrain
Z_LO, Z_HI = GAP, 5.2     # physical height-field range (data = (z - Z_LO) / (Z_HI - Z_LO)), above every obstacle
HFIELD_BASE = 0.1


def pick(key: jax.Array, values: jax.Array, shape: tuple[int, ...] = ()) -> jax.Array:
    """Entries of `values` drawn uniformly: `jax.random.choice`'s draw (an int32 index) made explicit, so that a
    terrain is the same under `jax.enable_x64` (float64 fidelity checks) as in float32."""
    return values[jax.random.randint(key, shape, 0, values.shape[0], jnp.int32)]


def cell_of(x: jax.Array, y: jax.Array) -> tuple[jax.Array, jax.Array]:
    """MetaMorph's `pos_to_idx` in unpadded cell coordinates."""
    return (START_COL + jnp.floor(x * DIVS)).astype(jnp.int32), (HALF_ROWS - jnp.floor(y * DIVS)).astype(jnp.int32)


# ---- the height-map observation grid (MetaMorph's wrappers/hfield.py) -------------------------------------------
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


# ---- the physical height-field patch ------------------------------------------------------------------------------
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

