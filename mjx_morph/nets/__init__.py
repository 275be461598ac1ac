"""mjx_morph.nets: the model zoo (MetaMorph, ModuMorph, R-MeMo, R-MoMo and ablations) in Flax.

    model = make_model("rmomo", hfield=False, decoder_dims=[])
    params = model.init(key, robots, obs_example)
    carry = model.initial_carry(num_envs)
    cache = model.robot_cache(params, robots)                # once per rollout (params fixed)
    mu, value, carry = model.step(params, robots, obs, carry, reset, cache=cache)
    mu, value, carry = model.sequence(params, robots, obs_seq, carry0, resets, burn_in=20)

Modules: layers (PyTorch-initialised Linear, MLP, pre-norm / fixed-attention encoder layer), recurrent
(LSTM and GRU cells with PyTorch's two biases), network (one actor or critic network, split into per-robot /
per-sample / recurrent phases), model (actor + critic, acting and training interface), zoo (architecture
table, make_model), distribution (frozen-std Gaussian).
"""
from . import distribution
from .distribution import ACTION_STD
from .model import Model, as_obs, example_obs, example_robots
from .network import NetConfig, PolicyNet
from .zoo import ARCHS, make_model

__all__ = ["ACTION_STD", "ARCHS", "Model", "NetConfig", "PolicyNet", "as_obs", "distribution", "example_obs",
           "example_robots", "make_model"]
