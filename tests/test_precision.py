"""The `precision` key (mjx_morph/nets/precision.py): what each mode computes, and that training runs in each.

- bf16 keeps float32 where precision.py promises it (parameters, carries, outputs) and its outputs stay within a
  stated tolerance of fp32 for every architecture (but the *_plus variants) at the paper's width (2 of the 5 layers, to compile quickly), over a
  sequence with burn-in;
- fp32 and tf32 differ only in the matmul precision XLA is asked for (on a CPU both compute float32);
- the jitted iteration runs in bf16 (each code path of the update) and in tf32, with the first minibatch after a
  rollout near ratio 1 (fp32's exact ratio-1 / KL-0 check for every architecture is tests/test_ppo_bookkeeping.py);
- the physics traces its matmuls at the highest precision whatever the networks use.
"""
from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_morph.nets import ARCHS, make_model
from mjx_morph.nets.model import example_obs, example_robots
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.ppo.trainer import Trainer
from mjx_morph.run import compose_run_config
from mjx_morph.run.build import make_model_for
from toy_env import ToyEnv

#: bf16 against fp32, per-limb means and values, relative to the largest fp32 output (measured worst: ~1.5%)
BF16_TOLERANCE = 0.04

T, B, BURN = 8, 4, 3
WIDE = dict(num_layers=2)     # the paper's d_model 128, ffn 1024, 2 heads


def _inputs(model):
    robots = example_robots(3, 7)
    robots = robots._replace(context=jax.random.normal(jax.random.key(1), robots.context.shape))
    obs = example_obs(model, (T, B))
    obs = obs._replace(proprio=jax.random.normal(jax.random.key(2), obs.proprio.shape),
                       prev_action=jax.random.uniform(jax.random.key(3), obs.prev_action.shape, minval=-1, maxval=1),
                       robot=jnp.broadcast_to(jnp.arange(B) % 3, (T, B)))
    resets = jnp.zeros((T, B), bool).at[0].set(True).at[5, 1].set(True)
    return robots, obs, resets


@pytest.mark.parametrize("arch", [a for a in ARCHS if not a.endswith("_plus")])   # _plus: one more MLP, same path
def test_bf16_outputs_match_fp32(arch):
    outs = {}
    for p in ("fp32", "bf16"):
        model = make_model(arch, hfield=False, decoder_dims=[], precision=p, **WIDE)
        robots, obs, resets = _inputs(model)
        params = model.init(jax.random.key(0), robots, jax.tree.map(lambda x: x[0], obs))
        # hyperrmomo's heads start at zero (the cell has no effect): move them as one update would
        params = jax.tree.map(lambda x: x + 0.01 * jax.random.normal(jax.random.key(4), x.shape), params)
        mu, value, carry = jax.jit(lambda pr, o: model.sequence(pr, robots, o, model.initial_carry(B), resets,
                                                                burn_in=BURN))(params, obs)
        assert all(x.dtype == jnp.float32 for x in jax.tree.leaves((params, mu, value, carry)))
        outs[p] = (np.asarray(mu), np.asarray(value))
    for k, name in enumerate(("mu", "value")):
        ref, got = outs["fp32"][k], outs["bf16"][k]
        scale = np.abs(ref).max()
        assert scale > 1e-3
        err = np.abs(got - ref).max() / scale
        assert err < BF16_TOLERANCE, f"{arch} {name}: bf16 off by {err:.3f} of the output scale"
        assert err > 1e-5, f"{arch} {name}: bf16 equal to fp32, so it did not compute in bfloat16"


def _dots(model) -> list[str]:
    """The parameters of every dot_general in one acting step (printed as `name:dtype[shape] = dot_general[...]`)."""
    robots, obs, resets = _inputs(model)
    o = jax.tree.map(lambda x: x[0], obs)
    params = jax.eval_shape(model.init, jax.random.key(0), robots, o)
    text = str(jax.make_jaxpr(lambda pr: model.step(pr, robots, o, model.initial_carry(B), resets[0]))(params))
    return re.findall(r"(\S+) = dot_general\[(.*?)\n\s*\]", text, flags=re.S)


def test_fp32_and_tf32_ask_for_their_matmul_precision():
    for p, mark in (("fp32", "Precision.HIGHEST"), ("tf32", "Precision.HIGH,")):   # HIGH: TF32 on GPUs
        dots = _dots(make_model("rmomo", hfield=False, decoder_dims=[], precision=p))
        assert len(dots) > 10 and all(mark in params for _, params in dots), p
    bf = _dots(make_model("rmomo", hfield=False, decoder_dims=[], precision="bf16"))
    assert sum("bf16[" in out for out, _ in bf) > len(bf) // 2       # most matmuls produce bfloat16


def test_precision_key_reaches_the_model_and_bad_values_are_refused():
    cfg = compose_run_config(["precision=bf16", "arch=modumorph"])
    assert make_model_for(cfg).net.precision == "bf16"
    with pytest.raises(ValueError, match="precision='fp16'"):
        compose_run_config(["precision=fp16"]).check()


TINY = dict(d_model=16, num_layers=1, num_heads=2, ffn_dim=32)
CFG = PPOConfig(num_envs=3, rollout_len=16, window=8, burn_in=4, minibatch_size=16, epochs=2)


@pytest.fixture(scope="module")
def env():
    return ToyEnv()


#: the update's two code paths in bf16 (feed-forward single transitions; windows with burn-in, LSTM + hypernetwork
#: tables); the forward pass of every architecture in bf16 is checked above, every architecture's update in fp32
#: by test_ppo_bookkeeping.py (each case here costs ~12 s of CPU compilation)
@pytest.mark.parametrize("arch,precision", [("metamorph", "bf16"), ("rmomo", "bf16"), ("rmomo", "tf32")])
def test_iteration_runs_in_each_precision(env, arch, precision):
    model = make_model(arch, hfield=False, decoder_dims=[], precision=precision, **TINY)
    trainer = Trainer(env, model, CFG, 3 * 16 * 4, fast_compile=True)
    ts = trainer.init(jax.random.PRNGKey(0))
    for _ in range(2):
        ts, m = trainer.iteration(ts)
    assert all(np.isfinite(float(v)) for k, v in m.items() if k not in ("episode_return", "episode_length",
                                                                        "fall_fraction"))
    floats = [x for x in jax.tree.leaves((ts.params, ts.opt_state, ts.carry)) if jnp.issubdtype(x.dtype, jnp.floating)]
    assert floats and all(x.dtype == jnp.float32 for x in floats)
    tol = 1e-4 if precision == "tf32" else 0.02      # acting (step) and training (sequence) round differently in bf16
    assert abs(float(m["first_ratio"]) - 1) < tol and abs(float(m["first_kl"])) < tol


def test_physics_matmuls_are_float32_whatever_the_networks_use():
    from mjx_morph.sim.env import make_env
    env = make_env("gen/train", "ft", self_collision=False)
    state = jax.eval_shape(lambda k: env.init(k, 2), jax.random.PRNGKey(0))       # traced, not compiled
    action = jax.ShapeDtypeStruct((2, 24), jnp.float32)
    text = str(jax.make_jaxpr(env.vstep)(state, action))
    dots = re.findall(r"= dot_general\[(.*?)\n\s*\]", text, flags=re.S)
    assert len(dots) > 10 and all("HIGHEST" in params for params in dots)
    with pytest.raises(ValueError, match="env.matmul_precision='tf32'"):
        make_env("gen/train", "ft", matmul_precision="tf32")
