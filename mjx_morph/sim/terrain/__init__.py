"""Terrain: the ground of each task, one object per kind, chosen once when the env is built.

    terr = terrain.for_task(task, robots)      # by `Task.terrain`: Plane, InclinedPlane, CorridorField, ObstacleField
    terr.world()                               # the task's MJCF around the robot (padding.WorldSpec)
    terr.origin                                # MetaMorph's coordinates of the simulation's origin
    terr.reference_world()                     # MetaMorph's own ground in that frame (MuJoCo C references)
    state = terr.generate(key)                 # the per-episode random terrain (NoTerrain for the planes)
    terr.ground_height(state, x, y)            # ground z under the torso (the torso height of the fall check)
    # height-field kinds only (terr.uses_hfield):
    terr.height(state, c, r)                   # MetaMorph's height array H at cells (c, r)
    terr.physical_height(state, c, r)          # surface z of the physics at the centre of cell (c, r)
    terr.patch(state, x, y)                    # the moving height-field patch centred under (x, y)
    terr.hfield_obs(state, x, y, yaw)          # the 1410-value height-map observation

Every method is pure JAX (jit / vmap), the terrain objects are static (frozen dataclasses holding Python
numbers). ft and incline are infinite planes (tasks.py), simulated in MetaMorph's world moved so that the torso
starts on the ground at the origin (`origin`, padding.WorldSpec: float32 resolves contacts there 8x finer on ft and
~60x on the incline than at MetaMorph's coordinates); positions, heights and `ground_height` are in that frame, and
the observation adds `origin` back, so the policy sees MetaMorph's numbers. The height-field kinds keep MetaMorph's
frame (origin 0). csr and obstacle are built on MetaMorph's height-array grid
(`grid.py`): `height` is `H` with its padding (csr: -10 outside the corridor; obstacle: walls 4 in a 10-cell ring
around the 1000 x 400 floor, -10 beyond), rounded to 3 decimals as MetaMorph rounds it; the torso height and the
observation read it, and the physics is one P x P height-field patch that follows the torso, refilled at every
control step from `physical_height` of the same cells, so what the policy sees is what the robot stands on. The
random terrains themselves are in `corridor.py` and `obstacles.py`, with their deviations from MetaMorph.

Deviation common to csr and obstacle (listed in `mjx_morph/sim/__init__.py`): the height field is the only ground
(MetaMorph's is one too); its contacts are MuJoCo C's height-field contacts (`hfield_contact.py`: one per prism a
geom penetrates), at most 32 per geom and 64 per env (all contacts), the deepest kept beyond.
"""
from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ...unimal.morphology import Morphology
from ..padding import WorldSpec
from . import corridor, grid, obstacles
from .corridor import Corridor
from .grid import DIVS, GAP, ROWS, Z_HI, Z_LO, cell_of

FLOOR_TOP = 1.0     # TERRAIN.SIZE[2]: MetaMorph's floor top (ft) and the slab's top where the incline's torso starts
from .obstacles import Obstacles


class NoTerrain(NamedTuple):
    """The per-episode state of the planes: nothing random."""


@dataclasses.dataclass(frozen=True)
class Terrain:
    """One kind of ground. Subclasses set `kind` (the `Task.terrain` name) and implement `world`,
    `ground_height` and, if random per episode, `generate`."""
    kind: ClassVar[str] = ""
    uses_hfield: ClassVar[bool] = False        # the physics is the moving height-field patch

    @classmethod
    def from_task(cls, task, robots: Sequence[Morphology]) -> Terrain:
        return cls()

    def world(self) -> WorldSpec:
        raise NotImplementedError

    def generate(self, key: jax.Array) -> Any:
        """A new random terrain for an episode."""
        return NoTerrain()

    def ground_height(self, state, x: jax.Array, y: jax.Array) -> jax.Array:
        """Ground z used for the torso height (MetaMorph's UnimalHeightObs), at (x, y) of the simulation's frame,
        in that frame."""
        raise NotImplementedError

    @property
    def origin(self) -> tuple[float, float, float]:
        """MetaMorph's coordinates of the simulation's origin (padding.WorldSpec.origin)."""
        return (0.0, 0.0, 0.0)

    def reference_world(self) -> WorldSpec:
        """`world()` with MetaMorph's own ground geometry (its floor boxes) for MuJoCo C references (fidelity.py);
        the same world where ours is MetaMorph's."""
        return self.world()


@dataclasses.dataclass(frozen=True)
class Plane(Terrain):
    """ft: an infinite plane, MetaMorph's floor top z = 1, simulated at z = 0 (origin (0, 0, 1))."""
    kind: ClassVar[str] = "plane"

    @property
    def origin(self):
        return (0.0, 0.0, FLOOR_TOP)

    def world(self) -> WorldSpec:
        return WorldSpec(geoms='    <geom name="floor" type="plane" size="0 0 1" pos="0 0 0" '
                               'contype="0" conaffinity="1"/>', origin=self.origin)

    def reference_world(self):
        # MetaMorph's floor: a box of half-height 1 centred at its world's origin
        return dataclasses.replace(self.world(), geoms=f'    <geom name="floor" type="box" size="100 100 1" '
                                   f'pos="0 0 {-self.origin[2]!r}" contype="0" conaffinity="1"/>')

    def ground_height(self, state, x, y):
        return jnp.float32(0.0)


@dataclasses.dataclass(frozen=True)
class InclinedPlane(Terrain):
    """incline: an infinite plane through the top face of MetaMorph's slab, tilted `incline_deg` about y (uphill
    along +x)."""
    kind: ClassVar[str] = "incline"
    incline_deg: float

    @classmethod
    def from_task(cls, task, robots):
        return cls(incline_deg=task.incline_deg)

    @property
    def origin(self):
        """The slab's top face below the torso's start: x = -73 cos(a), z = 1 - 73 sin(a) in MetaMorph's world."""
        a = np.radians(self.incline_deg)
        return (float(-73.0 * np.cos(a)), 0.0, float(FLOOR_TOP - 73.0 * np.sin(a)))

    def world(self) -> WorldSpec:
        a = np.radians(self.incline_deg)
        # the slab's top face in MetaMorph's world, z = 1/cos(a) + tan(a) x, is z = tan(a) x + 1/cos(a) - 1 here
        # (its point above the origin given as the plane's position, so no large coordinate enters its contacts)
        return WorldSpec(geoms=f'    <geom name="floor" type="plane" size="0 0 1" '
                               f'pos="0 0 {float(1 / np.cos(a) - 1)!r}" euler="0 {-float(self.incline_deg)!r} 0" '
                               'contype="0" conaffinity="1"/>', incline_deg=self.incline_deg, origin=self.origin)

    def reference_world(self):
        # MetaMorph's slab: a 150 m x 40 m x 2 m box centred at its world's origin, tilted about y
        ox, oy, oz = self.origin
        return dataclasses.replace(self.world(), geoms=f'    <geom name="floor" type="box" size="75 20 1" '
                                   f'pos="{-ox!r} {-oy!r} {-oz!r}" euler="0 {-float(self.incline_deg)!r} 0" '
                                   'contype="0" conaffinity="1"/>')

    def ground_height(self, state, x, y):
        # H = 1 + tan(a) (col/10 - 75) over the 1500 slab columns, -10 padding beyond; not clipped at 0
        ox, _, oz = self.origin
        col = jnp.floor((x + ox) * DIVS)
        h = 1.0 + np.tan(np.radians(self.incline_deg)) * col / DIVS
        h = jnp.round(h, 3)
        return jnp.where((col >= -750) & (col < 750), h, GAP) - oz


@dataclasses.dataclass(frozen=True)
class HeightField(Terrain):
    """A random terrain on MetaMorph's height-array grid, simulated as a `patch_size` x `patch_size` height field
    that follows the torso. Subclasses implement `generate`, `height` and `physical_height`."""
    uses_hfield: ClassVar[bool] = True
    patch_size: int                            # vertices per side of the physical patch (odd)

    @classmethod
    def from_task(cls, task, robots):
        return cls(patch_size=grid.patch_size(robots))

    def height(self, state, c: jax.Array, r: jax.Array) -> jax.Array:
        """MetaMorph's height array H at cells (c, r) (padding included, rounded to 3 decimals)."""
        raise NotImplementedError

    def physical_height(self, state, c: jax.Array, r: jax.Array) -> jax.Array:
        """Surface z of the physics at the centre of cell (c, r)."""
        raise NotImplementedError

    def local(self, state, ct: jax.Array, rt: jax.Array):
        """The part of `state` that can matter within reach of cell (ct, rt) (all of it by default)."""
        return state

    def world(self) -> WorldSpec:
        asset, geom = grid.hfield_world_xml(self.patch_size)
        return WorldSpec(assets=asset, geoms=geom)

    def patch(self, state, x: jax.Array, y: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Height-field data (P*P,) and geom position (3,) of the patch centred on the cell of (x, y)."""
        p = self.patch_size
        ct, rt = cell_of(x, y)
        state = self.local(state, ct, rt)
        h = (p - 1) // 2
        i = jnp.arange(p)
        c = ct - h + i                     # vertex column i  -> cell column
        r = rt + h - i                     # vertex row j     -> cell row (row j grows toward +y, cell rows toward -y)
        z = self.physical_height(state, c[None, :], r[:, None])         # (row j, column i)
        data = jnp.clip((z - Z_LO) / (Z_HI - Z_LO), 0.0, 1.0).reshape(-1)
        cx = -3.0 + ct.astype(jnp.float32) / DIVS + 0.5 / DIVS
        cy = (grid.HALF_ROWS - rt).astype(jnp.float32) / DIVS + 0.5 / DIVS
        return data.astype(jnp.float32), jnp.stack([cx, cy, jnp.float32(Z_LO)])

    def hfield_obs(self, state, x: jax.Array, y: jax.Array, yaw: jax.Array) -> jax.Array:
        """The 1410 height-map values relative to the ground under the torso, grid rotated by the torso yaw."""
        ct, rt = cell_of(x, y)
        state = self.local(state, ct, rt)
        cos, sin = jnp.cos(yaw), jnp.sin(yaw)
        dc = jnp.round(cos * grid.MASK_COL + sin * grid.MASK_ROW).astype(jnp.int32)
        dr = jnp.round(-sin * grid.MASK_COL + cos * grid.MASK_ROW).astype(jnp.int32)
        return self.height(state, ct + dc, rt + dr) - self.height(state, ct, rt)

    def ground_height(self, state, x, y):
        ct, rt = cell_of(x, y)
        return jnp.maximum(self.height(self.local(state, ct, rt), ct, rt), 0.0)


@dataclasses.dataclass(frozen=True)
class CorridorField(HeightField):
    """csr: a new random corridor per episode (`corridor.py`), a -10 m gap around it."""
    kind: ClassVar[str] = "corridor"

    def generate(self, key: jax.Array) -> Corridor:
        return corridor.generate(key)

    def height(self, state: Corridor, c, r):
        inside, h = corridor.profile(state, c, r)
        h = jnp.where(inside, h, GAP)
        return jnp.round(h.astype(jnp.float32), 3)

    def physical_height(self, state: Corridor, c, r):
        inside, h = corridor.profile(state, c, r)
        return jnp.where(inside, h, GAP)


@dataclasses.dataclass(frozen=True)
class ObstacleField(HeightField):
    """obstacle: the floor, its walls and 50 random boxes per episode (`obstacles.py`), a -10 m gap beyond the
    walls. Only the boxes near the torso are looked at (`obstacles.near`)."""
    kind: ClassVar[str] = "obstacles"

    def generate(self, key: jax.Array) -> Obstacles:
        return obstacles.generate(key)

    def local(self, state: Obstacles, ct, rt) -> Obstacles:
        return obstacles.near(state, ct, rt)

    @staticmethod
    def _floor_and_ring(c, r):
        floor = (c >= 0) & (c < obstacles.OBS_COLS) & (r >= 0) & (r < ROWS)
        w = obstacles.WALL_CELLS
        ring = (c >= -w) & (c < obstacles.OBS_COLS + w) & (r >= -w) & (r < ROWS + w)
        return floor, ring

    def height(self, state: Obstacles, c, r):
        floor, ring = self._floor_and_ring(c, r)
        h = jnp.where(floor, 1.0, jnp.where(ring, obstacles.WALL_OBS, GAP))
        h = jnp.where(obstacles.in_any_box(state, c, r), obstacles.OBSTACLE_OBS, h)
        return jnp.round(h.astype(jnp.float32), 3)

    def physical_height(self, state: Obstacles, c, r):
        floor, ring = self._floor_and_ring(c, r)
        h = jnp.where(floor, 1.0, jnp.where(ring, obstacles.WALL_TOP, GAP))
        return jnp.where(obstacles.in_any_box(state, c, r), obstacles.OBSTACLE_TOP, h)


KINDS: dict[str, type[Terrain]] = {t.kind: t for t in (Plane, InclinedPlane, CorridorField, ObstacleField)}


def for_task(task, robots: Sequence[Morphology] = ()) -> Terrain:
    """The terrain of `task` (a `tasks.Task`, by its `terrain` name), sized for `robots` (the height-field patch
    must reach every point of every robot; without robots it only covers the torso)."""
    if task.terrain not in KINDS:
        raise ValueError(f"unknown terrain {task.terrain!r}; expected one of {', '.join(KINDS)}")
    return KINDS[task.terrain].from_task(task, tuple(robots))

