"""mjx_morph.run: a training run, above the algorithm.

    config     `RunConfig`, the schema of a run (its parts: sim.EnvConfig, nets.ModelOptions, ppo.PPOConfig);
               composing it from command-line overrides, reading a run's saved config
    build      config -> `Experiment` (robots, env, model, trainer)
    run_dir    one directory per run: config.yaml, metrics (CSV + TensorBoard), Orbax checkpoints
    loop       `train(cfg)`: resume, iterate, report through callbacks (metrics, progress, checkpoints, figures)
    load       `load_run(run_dir)`: a run's config, objects and a checkpoint's train state, for evaluation
    figures    the learning curve a run draws for itself
    compile_cache  JAX's persistent compilation cache for the command-line tools
"""
from ..ppo.trainer import FAST_COMPILE, normalize_obs  # what evaluation needs of the learner: the policy's
#                                                         observation normalisation, the CPU compile options
from .build import Experiment, build, make_env_for, make_model_for, train_robots
from .compile_cache import DEFAULT_COMPILE_CACHE, use_compile_cache
from .config import CONF_DIR, ConfigError, RunConfig, compose, register, compose_run_config, read_run_config, to_dict, to_schema
from .load import LoadedRun, load_run
from .loop import (UNHEALTHY, Callback, Checkpoints, HealthWarnings, Loop, MetricsLog, ProgressBar, ProgressLines,
                   Summary, default_callbacks, train, unhealthy_reason)
from .run_dir import RunDir, RunDirError

__all__ = ["CONF_DIR", "UNHEALTHY", "DEFAULT_COMPILE_CACHE", "FAST_COMPILE", "normalize_obs", "Callback", "Checkpoints", "ConfigError", "HealthWarnings", "Experiment", "LoadedRun", "Loop", "MetricsLog",
           "ProgressBar", "ProgressLines", "RunConfig", "RunDir", "RunDirError", "Summary", "build", "compose", "compose_run_config",
           "default_callbacks", "load_run", "make_env_for", "make_model_for", "read_run_config", "register", "to_dict",
           "to_schema", "train", "train_robots", "unhealthy_reason", "use_compile_cache"]
