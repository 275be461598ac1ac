"""experiments/burn_in_staleness.py on the toy env with long episodes and a tiny R-MoMo: its machinery against
plain `model.advance`, and what it measures: after one update, the acting state re-derived by a longer burn-in is
closer to the state under the new parameters (and so is the policy)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import burn_in_staleness as bis
from mjx_morph.nets import make_model
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.ppo.trainer import Trainer
from mjx_morph.run import compose
from toy_env import ToyEnv

TINY = dict(d_model=16, num_layers=1, num_heads=2, ffn_dim=32)
CFG = PPOConfig(num_envs=8, rollout_len=16, window=8, burn_in=4, minibatch_size=32, epochs=2, lr=3e-3,
                warmup_iters=0)
LENGTHS = [0, 4, 8, 16, 32]
HISTORY = 64


@pytest.fixture(scope="module")
def env():
    return ToyEnv(limits=(200, 250, 300), fall_prob=0.005)     # episodes mostly longer than the history


@pytest.fixture(scope="module")
def trainer(env):
    return Trainer(env, make_model("rmomo", hfield=False, decoder_dims=[], **TINY), CFG, 10**6, fast_compile=True)


@pytest.fixture(scope="module")
def result(trainer):
    return bis.staleness(trainer, trainer.init(jax.random.PRNGKey(0)), LENGTHS, HISTORY)


def test_staleness_shrinks_as_the_burn_in_grows(result):
    """The differences to the reference (the state under the new parameters) of the states, policy means,
    KL and log-probs fall as the burn-in grows (monotone within 5%), from a clear gap without burn-in (the update
    changed the state) to a small one at the longest burn-in; most envs' episodes began before each burn-in,
    and the recorded live state is exact."""
    assert result["live_check"] < 1e-5
    for key in ("state_rel", "mu_rel", "kl", "abs_dlogp"):
        x = result[key]
        assert all(b <= 1.05 * a + 1e-9 for a, b in zip(x, x[1:])), (key, x)
    s = result["state_rel"]
    assert s[0] > 0.05, s
    assert s[-1] < 0.1 * s[0], s
    assert result["kl"][0] > 10 * result["kl"][-1] and result["kl"][0] > 0
    assert min(result["stale_envs"]) > 0.5, result["stale_envs"]
    table = bis.format_table(result)
    assert len(table.splitlines()) == 3 + len(LENGTHS)


def test_burn_in_states_equal_plain_advance(trainer, env):
    """`_burn_in_states` (one scan for every switch time at once) equals `model.advance` run with the old
    parameters up to the switch and with the new ones after it."""
    model = trainer.model
    ts = trainer.init(jax.random.PRNGKey(1))
    _, _, obs, first, start = bis.record(trainer, ts, 32)
    p_old = ts.params
    p_new = jax.tree.map(lambda x: 1.1 * x, p_old)
    switch = [0, 20, 32]
    states = bis._burn_in_states(model, env.robots, p_old, p_new, obs, first, start, jnp.asarray(switch))
    part = lambda a, b: jax.tree.map(lambda x: x[a:b], obs)              # noqa: E731
    for i, t in enumerate(switch):
        s = model.advance(p_old, env.robots, part(0, t), start, first[:t]) if t else start
        if t < 32:
            s = model.advance(p_new, env.robots, part(t, 32), s, first[t:])
        for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[i], states)), jax.tree.leaves(s)):
            np.testing.assert_allclose(a, b, atol=1e-5)
    # the switch matters: new parameters throughout differ from old parameters throughout
    assert not np.allclose(np.asarray(states["actor"]["h"][0]), np.asarray(states["actor"]["h"][2]), atol=1e-3)


def test_feed_forward_model_is_refused(env):
    trainer = Trainer(env, make_model("metamorph", hfield=False, decoder_dims=[], **TINY), CFG, 10**6)
    with pytest.raises(ValueError, match="feed-forward"):
        bis.staleness(trainer, None, LENGTHS)


def test_command_line_config(capsys):
    cfg = compose("burn_in_staleness", ["robots=gen/train", "preset=smoke", "lengths=[0,20,200]"],
                  bis.StalenessConfig)
    assert cfg.lengths == [0, 20, 200] and cfg.history is None and cfg.model.d_model == 16
    assert bis.main(["--help"]) == 0
    assert "pretrain_iters" in capsys.readouterr().out
