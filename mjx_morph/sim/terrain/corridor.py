"""The csr task's corridor: 110 m of flat pieces, curved slopes, steps and rugged squares, one random corridor per
episode (MetaMorph's terrain.py with csr.yaml), as a list of segments over the columns of the height-array grid
(`grid.py`). `profile` gives its surface at any cell; `terrain.CorridorField` turns that into MetaMorph's height
array and the physics.

Deviations from MetaMorph (listed in `mjx_morph/sim/__init__.py`):
- one 0.1 m vertex grid for the whole corridor (MetaMorph: boxes for the flat parts and one height field per
  segment whose vertex spacing is 2L/(20L - 1), slightly over 0.1 m); step edges and the segment ends are
  0.1 m ramps between vertex values, as inside MetaMorph's segments.
- rugged squares: MuJoCo stores height-field row 0 at -y while `H` has row 0 at +y, so in MetaMorph the observed
  map of a rugged-square segment is the y-mirror of the simulated one. We do **not** replicate this: the physics
  is built from the observed array, so observation and terrain agree (the band layout is random and symmetric in
  distribution, so the task is the same).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .grid import DIVS, ROWS, START_COL, pick

CSR_COLS = 1100           # 2 * 55 m
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


def generate(key: jax.Array) -> Corridor:
    """A new random corridor, drawn as MetaMorph draws it: after the 6 m start, repeat {flat piece of 2-6 m
    (truncated at the end), then a curve_slope / steps / rugged_square segment, skipped if it would overrun} until
    110 m are covered."""
    k_loop, k_rug = jax.random.split(key)

    def body(carry, k):
        end, nrug = carry
        kt, kf, kh, kc = jax.random.split(k, 4)
        active = end < CSR_COLS
        typ = pick(kt, jnp.array([CURVE, RUGGED, STEPS], jnp.int32))
        flat = pick(kf, jnp.asarray(FLAT_HALF_LEN, jnp.int32)) * 2 * DIVS
        flat = jnp.where(active, jnp.minimum(flat, CSR_COLS - end), 0)
        end1 = end + flat
        half = jnp.where(typ == STEPS, pick(kh, jnp.asarray(STEP_HALF_LEN, jnp.int32)),
                         pick(kh, jnp.asarray(HFIELD_HALF_LEN, jnp.int32)))
        ncol = half * 2 * DIVS
        ok = active & (end1 + ncol <= CSR_COLS)
        end2 = end1 + jnp.where(ok, ncol, 0)
        height = pick(kc, jnp.asarray(CURVE_HEIGHT, jnp.float32))
        rug = jnp.minimum(nrug, MAX_RUGGED - 1)
        seg = (jnp.stack([end1, end2]), jnp.stack([FLAT, typ]), jnp.stack([0.0, height]), jnp.stack([0, rug]))
        return (end2, nrug + (ok & (typ == RUGGED))), seg

    keys = jax.random.split(k_loop, MAX_ITERS)
    _, (end, kind, height, rug) = jax.lax.scan(body, (jnp.int32(2 * START_COL), jnp.int32(0)), keys)
    cat = lambda first, x: jnp.concatenate([jnp.asarray([first], x.dtype), x.reshape(-1)])
    kw, kf, kc = jax.random.split(k_rug, 3)
    widths = jax.random.randint(kw, (MAX_RUGGED, MAX_BANDS), 10, 20, jnp.int32)
    return Corridor(seg_end=cat(2 * START_COL, end).astype(jnp.int32), seg_kind=cat(FLAT, kind).astype(jnp.int32),
                    seg_height=cat(0.0, height).astype(jnp.float32), seg_rug=cat(0, rug).astype(jnp.int32),
                    band_end=jnp.cumsum(widths, axis=1).astype(jnp.int32),
                    band_f=pick(kf, jnp.asarray(RUGGED_F, jnp.float32), (MAX_RUGGED, MAX_BANDS)),
                    band_clip=pick(kc, jnp.asarray(RUGGED_CLIP, jnp.float32), (MAX_RUGGED, MAX_BANDS)))


def _sawtooth_half(t: jax.Array) -> jax.Array:
    """scipy.signal.sawtooth(t, width=0.5): -1 at 0, +1 at pi, -1 at 2 pi."""
    t = jnp.mod(t, 2 * jnp.pi)
    return jnp.where(t < jnp.pi, -1.0 + 2.0 * t / jnp.pi, 3.0 - 2.0 * t / jnp.pi)


def profile(tc: Corridor, c: jax.Array, r: jax.Array) -> tuple[jax.Array, jax.Array]:
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
