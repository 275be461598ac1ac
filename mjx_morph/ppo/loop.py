"""The training loop around the jitted iteration: it only builds, logs, checkpoints and plots.

`train(cfg)` takes the resolved config of `python -m experiments.run` (a plain dict or OmegaConf node):
builds the robot set, the env, the model and the trainer; resumes from the newest checkpoint in the run directory
if there is one; then runs iterations, logging one row per iteration (CSV + TensorBoard), showing a progress bar
with env steps/s and ETA, checkpointing every `checkpoint_every` iterations and at the end (also on Ctrl-C), and
writing the learning curve at the end. A resumed run ends where an uninterrupted one would: the whole train state
(parameters, optimiser, normalisers, sampler, env and recurrent state, keys) is in the checkpoint.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import jax

from ..eval.plots import learning_curve
from ..nets import model_from_config
from ..nets.context import mask_context
from ..sim.env import EnvConfig, make_env
from ..unimal.sets import default_train_set, load_set
from .run_dir import RunDir
from .trainer import PPOConfig, Trainer

#: config keys that shape the train state: a resume must agree on them
IDENTITY = ("env", "arch", "robots", "robots_root", "num_robots", "seed", "model_overrides", "context_features",
            "ppo.num_envs",
            "ppo.rollout_len", "ppo.window", "ppo.burn_in", "ppo.minibatch_size", "ppo.sampling")


def _plain(cfg: Any) -> dict:
    if hasattr(cfg, "_metadata"):
        from omegaconf import OmegaConf
        return OmegaConf.to_container(cfg, resolve=True)
    return dict(cfg)


def use_compile_cache(path: str | Path | None, min_compile_s: float = 2.0) -> Path | None:
    """Keep compiled XLA programs in `path` across processes (JAX's persistent compilation cache), so a resumed run
    or a second evaluation skips most compilation (H100, modumorph: first iteration 90 s fresh, 21 s resumed).
    Must run before the first compilation of the process; None or "" leaves the cache off."""
    if not path:
        return None
    p = Path(path).expanduser()
    p.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(p))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_s))
    return p


_BUILT: dict[str, tuple] = {}


def build(cfg: dict):
    """(env, model, trainer, robot set name) for a resolved config. Cached per process on the keys that shape
    the compiled programs, so a resumed run in the same process (tests, notebooks) reuses the compilation."""
    import json
    key = json.dumps({k: cfg.get(k) for k in ("env", "arch", "robots", "robots_root", "num_robots",
                                               "model_overrides", "context_features", "ppo", "total_steps",
                                               "fast_compile")},
                     sort_keys=True, default=str)
    if key not in _BUILT:
        _BUILT[key] = _build(cfg)
    return _BUILT[key]


def _build(cfg: dict):
    robots = cfg.get("robots") or default_train_set(cfg.get("robots_root"))
    rs = load_set(robots, cfg.get("robots_root"))
    chosen = rs.robots[: cfg["num_robots"]] if cfg.get("num_robots") else rs.robots
    env = make_run_env(cfg, chosen)
    model = model_from_config(_Attr(cfg["arch"]), _Attr(cfg["env"]), **(cfg.get("model_overrides") or {}))
    fields = {f.name for f in dataclasses.fields(PPOConfig)}
    unknown = set(cfg["ppo"]) - fields
    if unknown:
        raise ValueError(f"unknown ppo option(s) {sorted(unknown)}; known: {sorted(fields)}")
    ppo = PPOConfig(**{**cfg["ppo"], "total_steps": int(cfg["total_steps"])})
    return env, model, Trainer(env, model, ppo, fast_compile=bool(cfg.get("fast_compile", False))), robots


def make_run_env(cfg: dict, robots, **env_overrides):
    """The env of a run's config for `robots` (training or evaluation): the run's task and simulator options
    (`env_overrides` replace EnvConfig fields, e.g. episode_length) and its context-feature mask."""
    config = dataclasses.replace(EnvConfig.from_cfg(cfg["env"]), **env_overrides)
    env = make_env(list(robots), config=config)
    env.robots = mask_context(env.robots, cfg.get("context_features"))
    return env


class _Attr(dict):
    __getattr__ = dict.__getitem__


def default_run_dir(cfg: dict) -> Path:
    return Path("runs") / f"{cfg['env']['name']}-{cfg['arch']['name']}-s{cfg['seed']}"


def train(cfg: Any) -> Path:
    cfg = _plain(cfg)
    run = RunDir(cfg.get("run_dir") or default_run_dir(cfg), cfg, IDENTITY)
    env, model, trainer, robots = build(cfg)
    pc = trainer.cfg
    num_iters = pc.num_iters
    print(f"[mjx_morph] {model.arch} on {cfg['env']['name']}: {env.num_robots} robots ({robots}), "
          f"{model.num_params():,} parameters, {pc.num_envs} envs x {pc.rollout_len} steps = "
          f"{pc.steps_per_iter:,} steps/iteration, {num_iters} iterations; run dir {run.path}", flush=True)
    ts = trainer.init(jax.random.PRNGKey(int(cfg["seed"])))
    latest = run.latest_step()
    if latest is not None:
        ts = run.restore(latest, ts)
        run.truncate_metrics(latest)
        print(f"[mjx_morph] resumed from {run.path / 'checkpoints' / str(latest)} (iteration {latest})", flush=True)
    start = int(ts.iteration)
    bar = None
    if cfg.get("progress", True) and start < num_iters:
        from tqdm import tqdm
        bar = tqdm(total=num_iters, initial=start, unit="it", dynamic_ncols=True, file=sys.stderr)
    every = max(1, int(cfg.get("checkpoint_every", 50)))
    # stop_after: end this invocation after that many iterations (with a checkpoint), as if interrupted
    stop = min(num_iters, start + int(cfg["stop_after"])) if cfg.get("stop_after") else num_iters
    # time_limit_min: end this invocation (with a checkpoint) once the next iteration would not fit in that time
    deadline = time.perf_counter() + 60.0 * float(cfg["time_limit_min"]) if cfg.get("time_limit_min") else None
    it = start
    slowest, timed_out = 0.0, False
    try:
        while it < stop:
            if deadline is not None and it > start and time.perf_counter() + 1.5 * slowest > deadline:
                timed_out = True
                if run.latest_step() != it:
                    run.save(it, ts)
                print(f"\n[mjx_morph] time limit reached at iteration {it}; checkpoint saved. "
                      f"Rerun the same command to resume.", file=sys.stderr, flush=True)
                break
            t0 = time.perf_counter()
            if cfg.get("phase_timing", True):
                ts, batch, m1 = trainer.rollout(ts)
                jax.block_until_ready(batch)
                t1 = time.perf_counter()
                ts, m2 = trainer.update(ts, batch)
                metrics = {**m1, **m2}
                jax.block_until_ready(ts.params)
                t2 = time.perf_counter()
                phases = {"rollout_sps": pc.steps_per_iter / (t1 - t0), "update_sps": pc.steps_per_iter / (t2 - t1)}
            else:
                ts, metrics = trainer.iteration(ts)
                jax.block_until_ready(ts.params)
                t2 = time.perf_counter()
                phases = {"rollout_sps": float("nan"), "update_sps": float("nan")}
            it = int(ts.iteration)
            if it > start + 1:             # the first iteration of an invocation includes compilation
                slowest = max(slowest, t2 - t0)
            row = {"iteration": it, "env_steps": it * pc.steps_per_iter,
                   **{k: float(v) for k, v in jax.device_get(metrics).items()},
                   "sps": pc.steps_per_iter / (t2 - t0), **phases, "wall_s": t2 - t0}
            run.log(row)
            if bar is not None:
                bar.set_postfix(ret=f"{row['episode_return']:.1f}", sps=f"{row['sps']:,.0f}", refresh=False)
                bar.update(1)
            if it % every == 0 or it == stop:
                run.save(it, ts)
        if timed_out:
            return run.path
    except KeyboardInterrupt:
        if int(ts.iteration) > (run.latest_step() or 0):
            run.save(int(ts.iteration), ts)
        print(f"\n[mjx_morph] interrupted at iteration {int(ts.iteration)}; checkpoint saved. "
              f"Rerun the same command to resume.", file=sys.stderr)
        raise
    finally:
        if bar is not None:
            bar.close()
        run.close()
    png = learning_curve(run.read_metrics(), run.path / "learning_curve.png",
                         title=f"{model.arch} on {cfg['env']['name']} ({env.num_robots} robots)")
    rows = run.read_metrics()
    if rows:
        last = rows[-1]
        print(f"[mjx_morph] done: {int(last['env_steps']):,} env steps; last mean episode return "
              f"{last.get('episode_return', float('nan')):.2f}; learning curve {png}", flush=True)
    return run.path


def load_run(run_dir: str | Path, step: int | None = None):
    """(cfg, env, model, trainer, train state, step) of a run directory's checkpoint `step` (default: newest).

    Restores into the abstract train state (`jax.eval_shape` of init): nothing is compiled or run for the
    training batch, so loading a run for evaluation costs only building its robot set and reading the arrays."""
    import yaml
    run_dir = Path(run_dir)
    cfg_file = run_dir / "config.yaml"
    if not cfg_file.exists():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no config.yaml)")
    cfg = yaml.safe_load(cfg_file.read_text())
    run = RunDir(run_dir, cfg, IDENTITY)
    env, model, trainer, _ = build(cfg)
    steps = run.manager.all_steps() if (run_dir / "checkpoints").exists() else []
    if not steps:
        raise FileNotFoundError(f"{run_dir / 'checkpoints'}: no checkpoint yet")
    if step is None:
        step = max(steps)
    elif step not in steps:
        raise FileNotFoundError(f"{run_dir / 'checkpoints'}: no checkpoint {step}; have {sorted(steps)}")
    like = jax.eval_shape(trainer._init_state, jax.random.PRNGKey(int(cfg["seed"])))
    ts = run.restore(step, like)
    run.close()
    return cfg, env, model, trainer, ts, step
