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
from .model import Model, Obs, Robots, as_obs, example_obs, example_robots
from .network import (ACTS_PER_TOKEN, CTX_DIM, HFIELD_DIM, NUM_ACTIONS, NUM_TOKENS, OBS_DIM, STATE_DIM,
                      STATE_FEATURES, NetConfig, PolicyNet)
from .zoo import ARCHS, describe, make_model, model_from_config

__all__ = [
    "ACTION_STD", "ACTS_PER_TOKEN", "ARCHS", "CTX_DIM", "HFIELD_DIM", "Model", "NUM_ACTIONS", "NUM_TOKENS",
    "NetConfig", "OBS_DIM", "Obs", "PolicyNet", "Robots", "STATE_DIM", "STATE_FEATURES", "as_obs", "describe",
    "distribution", "example_obs", "example_robots", "make_model", "model_from_config",
]
