"""Recurrent PPO bookkeeping for every architecture, on a cheap synthetic env with the MJX env's interface:
after a rollout, recomputing every window (burn-in from the stored state, resets inside windows, the tail of the
previous rollout) with the same parameters must reproduce the stored log-probabilities and values exactly, so the
first minibatch has ratio 1 and KL 0."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from mjx_morph.nets import ARCHS, make_model
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.ppo.trainer import Trainer
from toy_env import ToyEnv

TINY = dict(d_model=16, num_layers=1, num_heads=2, ffn_dim=32)
CFG = PPOConfig(num_envs=3, rollout_len=16, window=8, burn_in=4, minibatch_size=16, epochs=2)
TOTAL_STEPS = 3 * 16 * 4


@pytest.fixture(scope="module")
def env():
    return ToyEnv()


@pytest.mark.parametrize("arch", ARCHS)
def test_first_minibatch_ratio_one_and_windows_reproduce_rollout(env, arch):
    model = make_model(arch, hfield=False, decoder_dims=[], precision="fp32", **TINY)   # the original arithmetic
    trainer = Trainer(env, model, CFG, TOTAL_STEPS, fast_compile=True)
    ts = trainer.init(jax.random.PRNGKey(0))
    for it in range(2):  # the second rollout's first windows burn in on the first rollout's tail
        params = ts.params
        ts, batch, roll = trainer.rollout(ts)
        logp, value, logp_old, value_old = trainer.evaluate_windows(params, batch)
        np.testing.assert_allclose(logp, logp_old, atol=2e-4, rtol=1e-5, err_msg=f"{arch} iteration {it}")
        np.testing.assert_allclose(value, value_old, atol=2e-5, rtol=1e-5, err_msg=f"{arch} iteration {it}")
        ts, m = trainer.update(ts, batch)
        assert abs(float(m["first_ratio"]) - 1.0) < 1e-4 and abs(float(m["first_kl"])) < 1e-4
        assert float(m["minibatches"]) == trainer.num_minibatches * CFG.epochs  # KL 0.05 never reached here
    assert float(roll["episodes"]) > 0  # episodes did end inside the rollout, so resets were exercised


@pytest.mark.parametrize("threshold,expect", [(-1.0, "none"), (1e-4, "some")])  # "all": the test above
def test_kl_early_stop(env, threshold, expect):
    model = make_model("metamorph", hfield=False, decoder_dims=[], **TINY)
    cfg = PPOConfig(**{**CFG.__dict__, "kl_threshold": threshold, "lr": 3e-2, "warmup_iters": 0})
    trainer = Trainer(env, model, cfg, TOTAL_STEPS, fast_compile=True)
    ts = trainer.init(jax.random.PRNGKey(1))
    before = ts.params
    ts, batch, _ = trainer.rollout(ts)
    ts, m = trainer.update(ts, batch)
    applied, total = int(m["minibatches"]), trainer.num_minibatches * cfg.epochs
    changed = any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(ts.params)))
    if expect == "none":
        assert applied == 0 and not changed  # the minibatch that crossed the threshold is not applied
    else:
        assert 1 <= applied < total and changed
