"""A memory task that only a correctly stored recurrent state can solve (tests/memory_env.py), trained with the real
`Trainer`: the reward at an episode's step t depends on a cue shown at step 0, and the score counts only steps
t >= window + burn-in, whose training sequences never contain their cue. A recurrent model (tiny R-MeMo) learns it;
a feed-forward one (tiny MetaMorph) cannot do better than chance (expected late return exactly 0).

This is the end-to-end check that the states stored where each window's burn-in starts (and the tail's) are
right. Measured with a subclass of `Trainer` whose `_rollout` zeroes `batch.starts` (this file's configuration,
seed 0, 50 iterations, KL stop off in both runs since it rejects every update once zeroed states matter): late
return -0.18 with zeroed stored states, 9.1 with the stored ones.
"""
from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from memory_env import MemoryEnv
from mjx_morph.nets import make_model
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.ppo.trainer import Trainer

TINY = dict(d_model=16, num_layers=1, num_heads=2, ffn_dim=32)
CFG = PPOConfig(num_envs=32, rollout_len=16, window=8, burn_in=4, minibatch_size=64, epochs=4, lr=1e-3,
                warmup_iters=0)
ITERS = 50            # measured late returns after 50 iterations (last 10 averaged), seeds 0-4: 6.2 to 9.4 of 12
LAST = 10             # iterations averaged for the score


@pytest.fixture(scope="module")
def env():
    env = MemoryEnv(length=24, reward_from=1, score_from=CFG.window + CFG.burn_in)
    assert env.length > env.score_from           # there are late steps to score
    return env


@functools.lru_cache(maxsize=None)
def late_return(env: MemoryEnv, arch: str, seed: int = 0) -> float:
    """Mean late return (rewards of steps >= window + burn-in) of the finished episodes of the last `LAST` of
    `ITERS` training iterations."""
    model = make_model(arch, hfield=False, decoder_dims=[], **TINY)
    trainer = Trainer(env, model, CFG, ITERS * CFG.steps_per_iter, fast_compile=True)
    ts = trainer.init(jax.random.PRNGKey(seed))
    returns = []
    for _ in range(ITERS):
        ts, m = trainer.iteration(ts)
        returns.append(float(m["episode_return"]))
    return float(np.nanmean(returns[-LAST:]))


def test_recurrent_model_remembers_a_cue_older_than_its_training_window(env):
    """R-MeMo's late return (at most 12: 12 scored steps, up to 1 each) rises far above chance."""
    assert late_return(env, "rmemo") > 4.0


def test_feed_forward_model_stays_at_chance(env):
    """MetaMorph sees no cue after step 0: its expected late return is 0 whatever it learns (the std of one
    iteration's mean is ~0.3 here)."""
    assert abs(late_return(env, "metamorph")) < 1.5
