"""Parameter count of a run's model, rebuilt from the run's config.

    counts = {}
    param_count(run.cfg, counts)        # trainable parameters (actor and critic); counts: memo over configurations
"""
from __future__ import annotations

import json

from ..run import make_model_for, to_schema


def param_count(cfg: dict, memo: dict[str, int] | None = None) -> int:
    """Trainable parameters of a run's model, built from its saved config as the run built it
    (`mjx_morph.run.make_model_for`; `Model.num_params` traces with jax.eval_shape, no compute). `memo` (the
    caller's) maps each model configuration counted to its count, so that a configuration is built once."""
    run = to_schema(cfg)
    key = json.dumps([run.arch, run.env.task, run.model.overrides()], sort_keys=True, default=str)
    memo = {} if memo is None else memo
    if key not in memo:
        memo[key] = make_model_for(run).num_params()
    return memo[key]
