"""Several seeds side by side (`seeds=[...]`, `Trainer(seeds=S)`): one vmapped program trains S independent runs.

Seed i of a side-by-side run must compute what seed i alone computes. On the CPU the two programs are not bit-equal:
XLA compiles the batched gradient matmuls and reductions with another summation order, so parameters drift by a few
float32 ulps (measured 1.5e-8 after one iteration of the toy config) and stay within `PARAM_TOLERANCE`. The KL stop is
per seed, and each seed is an ordinary run directory that can be resumed alone."""
from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
import yaml

from mjx_morph.nets import make_model
from mjx_morph.ppo.config import PPOConfig
from mjx_morph.ppo.trainer import Trainer, seed_keys, seed_state
from mjx_morph.run import Experiment, RunConfig, RunDir, RunDirError, train
from toy_env import ToyEnv

TINY = dict(d_model=16, num_layers=1, num_heads=2, ffn_dim=32)
PPO = PPOConfig(num_envs=8, rollout_len=16, window=8, burn_in=4, minibatch_size=32, epochs=2)
TOTAL = 8 * 16 * 10
#: after 2 iterations of the toy config (reassociated float32 sums, as for several devices in test_devices.py)
PARAM_TOLERANCE = 1e-6
KL = 2e-4            # tight enough that the KL stop fires within the first iterations, at different minibatches


def max_diff(a, b) -> float:
    return max((float(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)).max())
                for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)) if np.size(x)), default=0.0)


def test_seeds_side_by_side_equal_seeds_alone():
    """R-MoMo (recurrent state, burn-in tails) with a KL stop that fires at a different minibatch in each seed: each
    seed still matches its own run."""
    model = make_model("rmomo", hfield=False, decoder_dims=[], precision="fp32", **TINY)
    cfg = dataclasses.replace(PPO, kl_threshold=KL)
    one = Trainer(ToyEnv(), model, cfg, TOTAL, fast_compile=True)
    many = Trainer(ToyEnv(), model, cfg, TOTAL, fast_compile=True, seeds=2)
    seeds = [3, 5]
    ts = many.init(seed_keys(seeds))
    alone = [one.init(jax.random.PRNGKey(s)) for s in seeds]
    counts, counts_alone = [], []
    for _ in range(2):
        ts, m = many.iteration(ts)
        counts.append(np.asarray(m["minibatches"]).tolist())
        outs = [one.iteration(a) for a in alone]
        alone = [o[0] for o in outs]
        counts_alone.append([float(o[1]["minibatches"]) for o in outs])
    assert counts == counts_alone
    assert np.asarray(ts.iteration).tolist() == [2, 2]
    for i in range(2):
        assert max_diff(seed_state(ts, i).params, alone[i].params) < PARAM_TOLERANCE
        assert max_diff(seed_state(ts, i).env.obs, alone[i].env.obs) < 1e-5
    assert max_diff(seed_state(ts, 0).params, seed_state(ts, 1).params) > 1e-3      # the seeds really differ
    assert any(c[0] != c[1] for c in counts) and min(map(min, counts)) < 8    # the stop fired, not alike


def test_seed_count_must_match_the_keys():
    model = make_model("metamorph", hfield=False, decoder_dims=[], precision="fp32", **TINY)
    many = Trainer(ToyEnv(), model, PPO, TOTAL, fast_compile=True, seeds=2)
    with pytest.raises(ValueError, match="expected 2 keys"):
        many.init(jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="seeds=0"):
        Trainer(ToyEnv(), model, PPO, TOTAL, seeds=0)


def toy_experiment(cfg: RunConfig) -> Experiment:
    env = ToyEnv()
    model = make_model(cfg.arch, hfield=False, decoder_dims=[], precision="fp32", **TINY)
    trainer = Trainer(env, model, cfg.ppo, cfg.total_steps, fast_compile=True,
                      seeds=None if cfg.seeds is None else len(cfg.seeds))
    return Experiment(cfg, "toy", (), env, model, trainer)


def toy_config(run_dir, **kw) -> RunConfig:
    return RunConfig(arch="metamorph", ppo=PPO, total_steps=TOTAL, run_dir=str(run_dir), progress=False,
                     precision="fp32", checkpoint_every=1, compile_cache=None, **kw)


def test_seed_runs_are_ordinary_run_directories(tmp_path):
    """Each seed writes its own config (seed = that seed), metrics and checkpoints; a seed resumes alone; seeds at
    different iterations are not stacked; run_dir must name the seed."""
    cfg = toy_config(tmp_path / "s{seed}", seeds=[0, 1], stop_at=2)
    paths = train(cfg, toy_experiment(cfg))
    assert paths == [(tmp_path / "s0").resolve(), (tmp_path / "s1").resolve()]
    rows = [RunDir(p).read_metrics() for p in paths]
    for s, (p, r) in enumerate(zip(paths, rows)):
        saved = yaml.safe_load((p / "config.yaml").read_text())
        assert saved["seed"] == s and saved["seeds"] is None and saved["run_dir"] == str(tmp_path / f"s{s}")
        assert [int(x["iteration"]) for x in r] == [1, 2] and RunDir(p).latest_step() == 2
    assert rows[0][-1]["loss"] != rows[1][-1]["loss"]

    # seed 1 alone, one more iteration: an ordinary resume of its directory
    alone = toy_config(tmp_path / "s1", seed=1, stop_at=3)
    train(alone, toy_experiment(alone))
    assert RunDir(paths[1]).latest_step() == 3
    with pytest.raises(RunDirError, match="different iterations"):
        cfg3 = toy_config(tmp_path / "s{seed}", seeds=[0, 1], stop_at=4)
        train(cfg3, toy_experiment(cfg3))
    assert RunDir(paths[0]).latest_step() == 2                    # nothing was changed
    with pytest.raises(ValueError, match=r"put \{seed\} in it"):
        train(toy_config(tmp_path / "same", seeds=[0, 1]), toy_experiment(toy_config(tmp_path, seeds=[0, 1])))
