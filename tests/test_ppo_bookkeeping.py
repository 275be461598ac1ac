"""Recurrent PPO bookkeeping for every architecture, on a cheap synthetic env with the MJX env's interface:
after a rollout, recomputing every window (burn-in from the stored state, resets inside windows, the tail of the
previous rollout) with the same parameters must reproduce the stored log-probabilities and values exactly, so the
first minibatch has ratio 1 and KL 0. That check is blind to a wrong stored tail state (the acting state is
re-derived by the same burn-in), so the live state is checked separately: with no update between two rollouts the
acting state the second re-derives from the tail equals the state the first one ended with."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_morph.nets import ARCHS, make_model
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.ppo.trainer import Trainer
from toy_env import ToyEnv

TINY = dict(d_model=16, num_layers=1, num_heads=2, ffn_dim=32)
CFG = PPOConfig(num_envs=3, rollout_len=16, window=8, burn_in=4, minibatch_size=16, epochs=2)
TOTAL_STEPS = 3 * 16 * 4
RECURRENT = tuple(a for a in ARCHS if make_model(a, hfield=False, decoder_dims=[]).recurrent)


@pytest.fixture(scope="module")
def env():
    return ToyEnv()


@functools.lru_cache(maxsize=None)
def trainer_for(env: ToyEnv, arch: str) -> Trainer:
    """One trainer per architecture (its jitted functions compile once), shared by the tests of this file; fp32,
    the original code's arithmetic, in which ratio 1 and KL 0 are exact."""
    model = make_model(arch, hfield=False, decoder_dims=[], precision="fp32", **TINY)
    return Trainer(env, model, CFG, TOTAL_STEPS, fast_compile=True)


@functools.lru_cache(maxsize=None)
def acting_fns(env: ToyEnv, arch: str):
    """Jitted `model.advance` (the burn-in the rollout runs over the tail) and `model.step` of `trainer_for`."""
    model = trainer_for(env, arch).model
    return jax.jit(model.advance), jax.jit(model.step)


@pytest.mark.parametrize("arch", ARCHS)
def test_first_minibatch_ratio_one_and_windows_reproduce_rollout(env, arch):
    trainer = trainer_for(env, arch)
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


@functools.lru_cache(maxsize=None)
def kl_trainer(env: ToyEnv, threshold: float) -> Trainer:
    """A metamorph trainer with the given KL threshold (and a large learning rate), shared by the tests below."""
    model = make_model("metamorph", hfield=False, decoder_dims=[], **TINY)
    cfg = PPOConfig(**{**CFG.__dict__, "kl_threshold": threshold, "lr": 3e-2, "warmup_iters": 0})
    return Trainer(env, model, cfg, TOTAL_STEPS, fast_compile=True)


@pytest.mark.parametrize("threshold,expect", [(-1.0, "none"), (1e-4, "some")])  # "all": the test above
def test_kl_early_stop(env, threshold, expect):
    trainer = kl_trainer(env, threshold)
    cfg = trainer.cfg
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



def test_first_minibatch_statistics_reported_when_the_kl_stop_rejects_it(env):
    """`first_ratio` / `first_kl` are the check that the stored states reproduce the rollout (ratio 1, KL 0 on the
    first minibatch). They report the first minibatch even when the KL stop rejects it, which is exactly when the
    check matters (with wrong stored states the first minibatch's KL exceeds the threshold). (Found by this test:
    the statistics used to be those of the minibatches while none was applied, so skipped minibatches' zeros
    overwrote a rejected first one.)"""
    trainer = kl_trainer(env, -1.0)            # every minibatch crosses the threshold
    ts, batch, _ = trainer.rollout(trainer.init(jax.random.PRNGKey(1)))
    _, m = trainer.update(ts, batch)
    assert int(m["minibatches"]) == 0
    assert abs(float(m["first_ratio"]) - 1.0) < 1e-4 and abs(float(m["first_kl"])) < 1e-4, m


def test_burn_in_longer_than_window_is_refused(env):
    """The rollout stores the state where each window's burn-in starts, found in the window before
    (`save_at = window - burn_in`); a burn-in longer than the window would need states further back, and used to
    be accepted with every stored start wrong (log-prob errors ~3e-3, live-state differences ~0.4)."""
    model = make_model("rmomo", hfield=False, decoder_dims=[], **TINY)
    cfg = PPOConfig(**{**CFG.__dict__, "window": 4, "burn_in": 6})
    with pytest.raises(ValueError, match="ppo.burn_in=6 exceeds ppo.window=4"):
        Trainer(env, model, cfg, TOTAL_STEPS, fast_compile=True)
    Trainer(env, model, PPOConfig(**{**CFG.__dict__, "window": 4, "burn_in": 4}), TOTAL_STEPS)   # equal is fine


def per_env_diff(a, b) -> np.ndarray:
    """(N,) the largest absolute difference of two carries per env, over every leaf (actor / critic, h / c)."""
    return np.max([np.abs(np.asarray(x) - np.asarray(y)).reshape(x.shape[0], -1).max(1)
                   for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b))], axis=0)


@pytest.mark.parametrize("arch", RECURRENT)
def test_rollouts_without_update_act_from_the_live_state(env, arch):
    """Rollouts with no update between them: the acting state each rollout starts from, re-derived by burning in
    over the stored tail (`model.advance` from `tail_carry` with the resets `tail_first`), equals the live state
    `carry` the previous rollout ended with, and the first step's stored value and log-probability equal those of
    a step from that live state. Episodes end inside some tails (resets during the burn-in) and not in others; the
    check is shown to bite on both: a zeroed `tail_carry` changes the state of the envs without a reset in the
    tail, a burn-in that ignores the resets changes the state of the envs with one."""
    trainer = trainer_for(env, arch)
    model, robots, b = trainer.model, env.robots, CFG.burn_in
    advance, step = acting_fns(env, arch)
    ts = trainer.init(jax.random.PRNGKey(3))
    no_reset_diff, reset_diff = [], []
    for i in range(4):
        prev = ts
        ts, batch, _ = trainer.rollout(ts)
        if i:
            # what this rollout did at its first step, against a step from the live state of the previous one
            obs0 = jax.tree.map(lambda x: x[b], batch.obs)
            mu, value, _ = step(prev.params, robots, obs0, prev.carry, prev.first)
            logp = model.log_prob(mu, batch.action[0], robots.act_mask[obs0.robot])
            np.testing.assert_allclose(value, batch.value[0], atol=1e-5, rtol=1e-5, err_msg=f"{arch} rollout {i}")
            np.testing.assert_allclose(logp, batch.logp[0], atol=1e-4, rtol=1e-5, err_msg=f"{arch} rollout {i}")
        # the state the next rollout will act from, against the live state this one ended with
        derived = advance(ts.params, robots, ts.tail_obs, ts.tail_carry, ts.tail_first)
        assert per_env_diff(derived, ts.carry).max() < 1e-5, f"{arch} rollout {i}"
        reset_in_tail = np.asarray(ts.tail_first).any(0)
        zeroed = advance(ts.params, robots, ts.tail_obs, jax.tree.map(jnp.zeros_like, ts.tail_carry), ts.tail_first)
        no_reset_diff.extend(per_env_diff(zeroed, ts.carry)[~reset_in_tail])
        no_resets = advance(ts.params, robots, ts.tail_obs, ts.tail_carry, jnp.zeros_like(ts.tail_first))
        reset_diff.extend(per_env_diff(no_resets, ts.carry)[reset_in_tail])
    assert no_reset_diff and reset_diff, "need envs with and without a reset in the tail"
    assert min(no_reset_diff) > 1e-3 and min(reset_diff) > 1e-3, (min(no_reset_diff), min(reset_diff))
