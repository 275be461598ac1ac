"""From a `RunConfig` to the objects of a run: robots, env, model and trainer (`Experiment`).

    exp = build(cfg)                 # cfg: RunConfig
    exp.env, exp.model, exp.trainer  # the trainer's jitted functions compile on first use
    env = make_env_for(cfg, robots, episode_length=200)   # the run's task and options for other robots (evaluation)

Building is the one place where a config becomes objects: `cfg.env` goes to the env, `cfg.arch` + `cfg.model` +
the task's facts (height map, decoder layers) to the model, `cfg.ppo` + `cfg.total_steps` to the trainer.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

from ..nets import Model, make_model
from ..ppo.trainer import Trainer
from ..sim.env import Env, make_env
from ..sim.tasks import get_task
from ..unimal.morphology import Morphology
from ..unimal.sets import default_train_set, load_set
from .config import RunConfig


@dataclasses.dataclass(frozen=True, eq=False)
class Experiment:
    """What a run's config builds. Keep it to reuse its compiled functions (tests, notebooks, evaluation)."""
    config: RunConfig
    robot_set: str                      # the robot set's name or path
    robots: tuple[Morphology, ...]      # the robots trained on (`num_robots` applied)
    env: Env
    model: Model
    trainer: Trainer


def train_robots(cfg: RunConfig) -> tuple[str, tuple[Morphology, ...]]:
    """(set name, robots) the run trains on: `robots` (default: the original train set if present, else
    gen/train), the first `num_robots` of them if set."""
    name = cfg.robots or default_train_set(cfg.robots_root)
    robots = load_set(name, cfg.robots_root, allow_outside_design_space=cfg.allow_outside_design_space).robots
    if cfg.num_robots is not None and not 1 <= cfg.num_robots <= len(robots):
        raise ValueError(f"num_robots={cfg.num_robots}: expected 1 to {len(robots)}, the size of {name}")
    return name, tuple(robots[: cfg.num_robots] if cfg.num_robots else robots)


def make_env_for(cfg: RunConfig, robots: Sequence[Morphology], **env_overrides) -> Env:
    """The env of the run's task and simulator options (`env_overrides` replace EnvConfig fields) for `robots`."""
    return make_env(list(robots), config=dataclasses.replace(cfg.env, **env_overrides))


def make_model_for(cfg: RunConfig) -> Model:
    """The run's architecture with its overrides, shaped for the task (height map, decoder layers)."""
    task = get_task(cfg.env.task)
    return make_model(cfg.arch, hfield=task.hfield_obs, decoder_dims=task.decoder_dims, precision=cfg.precision,
                      **cfg.model.overrides())


def build(cfg: RunConfig) -> Experiment:
    """Everything a run's config describes, validated: bad values, robot files, model options and batch
    geometry fail here, before anything is written."""
    cfg.check()
    name, robots = train_robots(cfg)
    env = make_env_for(cfg, robots)
    model = make_model_for(cfg)
    trainer = Trainer(env, model, cfg.ppo, cfg.total_steps, fast_compile=cfg.fast_compile, devices=cfg.devices,
                      seeds=None if cfg.seeds is None else len(cfg.seeds))
    return Experiment(cfg, name, robots, env, model, trainer)
