"""Which robot an env gets at its next reset: MetaMorph's balanced sampling, or uniform.

Balanced (MetaMorph's "balanced_replay_buffer"): per robot i an episode-length estimate l_i: the mean of its
first 10 episodes, then an EMA l_i <- 0.1 l + 0.9 l_i per finished episode (in time order). For the first
30 PPO iterations every robot is equally likely; afterwards p_i ~ (1000 / l_i)^1, so robots whose episodes end
early are sampled more and each robot contributes a similar number of transitions. MetaMorph writes a list of
robot ids after every iteration that its envs read at reset; drawing each reset's robot i.i.d. from p, with p fixed
during an iteration, is the same distribution.

Guard (MetaMorph leaves l_i = -1 until robot i has 10 episodes, which would give a negative probability): a robot
with 1-9 episodes uses the mean of the episodes it has, a robot with none the smallest estimate of the others (the
largest probability), so that it gets sampled and measured.

The state is held by the training loop: `update(state, lengths, robots, done)` once per iteration with the
rollout's finished episodes (arrays of any shape, flattened in time-major order), and the env's `step` reads
`state.probs` at every auto-reset. Everything is jit-able; `update` sorts the episodes by robot once (no scan).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

UNIFORM_ITERS = 30
EMA_ALPHA = 0.1
PROB_ALPHA = 1.0
INIT_EPISODES = 10
MAX_LEN = 1000.0


class SamplerState(NamedTuple):
    probs: jax.Array       # (R,) float32, sums to 1
    iteration: jax.Array   # () int32, PPO iterations done
    count: jax.Array       # (R,) int32 finished episodes per robot
    init_sum: jax.Array    # (R,) float32 sum of the first <= 10 episode lengths
    ep_len: jax.Array      # (R,) float32 EMA estimate (valid once count >= 10)
    balanced: jax.Array    # () bool; False = uniform forever


def init(num_robots: int, mode: str = "balanced") -> SamplerState:
    if mode not in ("balanced", "uniform"):
        raise ValueError(f"sampling mode {mode!r}: expected 'balanced' or 'uniform'")
    r = num_robots
    return SamplerState(probs=jnp.full((r,), 1.0 / r, jnp.float32), iteration=jnp.int32(0),
                        count=jnp.zeros((r,), jnp.int32), init_sum=jnp.zeros((r,), jnp.float32),
                        ep_len=jnp.full((r,), -1.0, jnp.float32), balanced=jnp.asarray(mode == "balanced"))


def sample(key: jax.Array, state: SamplerState | None, num_robots: int) -> jax.Array:
    """One robot index (int32) drawn from the sampler's probabilities (uniform without a sampler).

    The draw is `jax.random.choice(key, num_robots, p=state.probs)`'s, index for index (inverse CDF: the first
    cumulative probability that reaches one uniform draw), but looked up by comparing against all R entries at once
    instead of `searchsorted`'s default loop: every env runs this at every step (the auto-reset's robot), and that
    loop was 2.3% of a 64-env rollout on an H200 (docs/benchmarks.md, session 59)."""
    if state is None:
        return jax.random.randint(key, (), 0, num_robots, dtype=jnp.int32)
    cdf = jnp.cumsum(state.probs)
    r = cdf[-1] * (1 - jax.random.uniform(key, (), dtype=cdf.dtype))
    return jnp.searchsorted(cdf, r, method="compare_all").astype(jnp.int32)


def _probs(iteration, count, init_sum, ep_len, balanced) -> jax.Array:
    r = count.shape[0]
    partial = init_sum / jnp.maximum(count, 1)
    est = jnp.where(count >= INIT_EPISODES, ep_len, partial)
    has = count > 0
    fallback = jnp.where(has.any(), jnp.min(jnp.where(has, est, jnp.inf)), MAX_LEN)
    est = jnp.maximum(jnp.where(has, est, fallback), 1.0)
    p = (MAX_LEN / est) ** PROB_ALPHA
    p = p / p.sum()
    uniform = jnp.full((r,), 1.0 / r, jnp.float32)
    return jnp.where(balanced & (iteration >= UNIFORM_ITERS), p, uniform).astype(jnp.float32)


def update(state: SamplerState, lengths: jax.Array, robots: jax.Array, done: jax.Array) -> SamplerState:
    """Fold one iteration's finished episodes into the estimates and recompute the probabilities.
    `lengths`, `robots`, `done`: same shape (e.g. (T, N) from the rollout's episode stats); entries with
    done = False are ignored. Episodes of one robot are folded in flattened (time-major) order."""
    r = state.count.shape[0]
    length = lengths.reshape(-1).astype(jnp.float32)
    key = jnp.where(done.reshape(-1), robots.reshape(-1).astype(jnp.int32), r)
    order = jnp.argsort(key, stable=True)
    rs, ls = key[order], length[order]
    valid = rs < r
    rsc = jnp.minimum(rs, r - 1)
    n = rs.shape[0]
    rank = jnp.arange(n) - jnp.searchsorted(rs, rs, side="left")
    seg = lambda v: jax.ops.segment_sum(v, rs, num_segments=r + 1)[:r]
    n_new = seg(valid.astype(jnp.int32))
    c_old = state.count
    g = c_old[rsc] + rank                                   # index of this episode among the robot's episodes
    init_sum = state.init_sum + seg(jnp.where(valid & (g < INIT_EPISODES), ls, 0.0))
    count = c_old + n_new
    first_ema = jnp.maximum(c_old, INIT_EPISODES)           # episodes before this index only built the mean
    m = jnp.maximum(count - first_ema, 0)                   # EMA updates this iteration
    start = jnp.where(c_old >= INIT_EPISODES, state.ep_len, init_sum / INIT_EPISODES)
    e = g - first_ema[rsc]
    w = EMA_ALPHA * (1.0 - EMA_ALPHA) ** (m[rsc] - 1 - e).astype(jnp.float32)
    ema_add = seg(jnp.where(valid & (g >= INIT_EPISODES), w * ls, 0.0))
    ep_len = jnp.where(count >= INIT_EPISODES, (1.0 - EMA_ALPHA) ** m.astype(jnp.float32) * start + ema_add,
                       state.ep_len)
    iteration = state.iteration + 1
    probs = _probs(iteration, count, init_sum, ep_len, state.balanced)
    return SamplerState(probs=probs, iteration=iteration, count=count, init_sum=init_sum, ep_len=ep_len,
                        balanced=state.balanced)
