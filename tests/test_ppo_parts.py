"""PPO building blocks against plain NumPy references."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_morph.ppo.gae import gae
from mjx_morph.ppo.loss import ppo_loss
from mjx_morph.ppo.schedule import learning_rate
from mjx_morph.ppo.stats import RewardScaler, RunningMeanStd


def gae_reference(values, rewards, dones, timeouts, last_value, gamma, lam):
    """Straight transcription of MetaMorph's Buffer.compute_returns loop."""
    T, N = values.shape
    adv = np.zeros((T, N))
    running = np.zeros(N)
    for t in reversed(range(T)):
        nxt = last_value if t == T - 1 else values[t + 1]
        mask, keep = 1.0 - dones[t], 1.0 - timeouts[t]
        delta = (rewards[t] + gamma * nxt * mask - values[t]) * keep
        running = delta + gamma * lam * mask * running
        adv[t] = running
    return adv, adv + values


def test_gae_matches_numpy_reference():
    rng = np.random.default_rng(0)
    T, N = 37, 5
    values, rewards, last = rng.normal(size=(T, N)), rng.normal(size=(T, N)), rng.normal(size=N)
    dones = rng.random((T, N)) < 0.15
    timeouts = dones & (rng.random((T, N)) < 0.5)
    adv, ret = gae(jnp.asarray(values), jnp.asarray(rewards), jnp.asarray(dones), jnp.asarray(timeouts),
                   jnp.asarray(last), 0.99, 0.95)
    ref_adv, ref_ret = gae_reference(values, rewards, dones.astype(float), timeouts.astype(float), last, 0.99, 0.95)
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(ret, ref_ret, rtol=1e-5, atol=1e-5)
    # a time-limit step has zero advantage and its own value as target
    t, n = np.argwhere(timeouts)[0]
    assert abs(adv[t, n]) < 1e-6 and abs(ret[t, n] - values[t, n]) < 1e-5


def test_running_mean_std_matches_batch_statistics():
    rng = np.random.default_rng(1)
    data = rng.normal(3.0, 2.0, size=(50, 8, 4))
    rms = RunningMeanStd.create((4,))
    for batch in data:
        rms = rms.update(jnp.asarray(batch))
    flat = data.reshape(-1, 4)
    np.testing.assert_allclose(rms.mean, flat.mean(0), rtol=1e-4)
    np.testing.assert_allclose(rms.var, flat.var(0), rtol=1e-3)
    x = rms.normalize(jnp.asarray(flat))
    assert float(jnp.abs(x.mean(0)).max()) < 1e-3 and float(jnp.abs(x.std(0) - 1).max()) < 1e-3
    assert float(rms.normalize(jnp.full((1, 4), 1e6)).max()) == 10.0  # clipped


def test_reward_scaler_divides_by_return_std_and_resets_on_done():
    scaler = RewardScaler.create(3)
    rewards = jnp.array([1.0, 2.0, 3.0])
    scaler, scaled = scaler(rewards, jnp.array([False, True, False]), 0.99)
    np.testing.assert_allclose(scaler.returns, [1.0, 0.0, 3.0])
    np.testing.assert_allclose(scaled, rewards / np.sqrt(scaler.stats.var + 1e-8), rtol=1e-6)


def test_learning_rate_warmup_and_cosine():
    lrs = np.array([learning_rate(i, 100) for i in range(100)])
    factors = lrs[:6] / (3e-4 * 0.5 * (1 + np.cos(np.pi * np.arange(6) / 100)))
    np.testing.assert_allclose(factors, [0.1, 0.28, 0.46, 0.64, 0.82, 1.0], rtol=1e-5)
    assert lrs[50] == pytest.approx(1.5e-4, rel=1e-5) and lrs[-1] < 1e-7 + 3e-4 * 0.5 * (1 + np.cos(np.pi * 0.99))


def test_ppo_loss_at_identical_policy():
    rng = np.random.default_rng(2)
    logp = jnp.asarray(rng.normal(size=64))
    adv, val, ret = (jnp.asarray(rng.normal(size=64)) for _ in range(3))
    info = ppo_loss(logp, logp, adv, val, val, ret, jnp.zeros(64))
    assert float(info.approx_kl) == 0.0 and float(info.ratio_mean) == 1.0 and float(info.clip_frac) == 0.0
    np.testing.assert_allclose(info.pi_loss, -adv.mean(), rtol=1e-6)
    np.testing.assert_allclose(info.v_loss, 0.5 * ((val - ret) ** 2).mean(), rtol=1e-6)
    # the clip bounds the gain from moving the ratio beyond 1 + eps
    moved = ppo_loss(logp + 0.5, logp, jnp.ones(64), val, val, ret, jnp.zeros(64))
    assert float(moved.pi_loss) == pytest.approx(-1.2) and float(moved.clip_frac) == 1.0


def test_shuffle_windows_blocks():
    """The minibatch shuffle: each epoch uses every window once; with G blocks each minibatch takes m = mb / G windows
    from each block (block-local ids); G = 1 is one plain permutation of all windows per epoch."""
    from mjx_morph.ppo.config import PPOConfig
    from mjx_morph.ppo.trainer import minibatch_blocks, shuffle_windows
    key, epochs, n_windows, mb = jax.random.PRNGKey(3), 2, 64, 16
    plain = np.asarray(shuffle_windows(key, epochs, n_windows, mb, 1))
    assert plain.shape == (epochs * n_windows // mb, 1, mb)
    perms = jax.vmap(lambda k: jax.random.permutation(k, n_windows))(jax.random.split(key, epochs))
    np.testing.assert_array_equal(plain.reshape(epochs, -1), np.asarray(perms))
    ids = np.asarray(shuffle_windows(key, epochs, n_windows, mb, 4))          # 4 blocks of 16 windows, m = 4
    assert ids.shape == (epochs * 4, 4, 4)
    for e in range(epochs):
        for g in range(4):
            assert sorted(ids[e * 4:(e + 1) * 4, g].ravel()) == list(range(16))   # each block's windows once
    cfg = PPOConfig(num_envs=8, minibatch_blocks=3)
    with pytest.raises(ValueError, match="ppo.minibatch_blocks=3: expected a divisor of ppo.num_envs=8"):
        minibatch_blocks(cfg, 4, 1)
    with pytest.raises(ValueError, match="a multiple of the 4 device"):
        minibatch_blocks(PPOConfig(num_envs=8, minibatch_blocks=2), 4, 4)
    assert minibatch_blocks(PPOConfig(num_envs=8), 4, 2) == 2 and minibatch_blocks(PPOConfig(num_envs=8), 4, 1) == 1
