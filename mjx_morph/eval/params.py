"""Parameter count of a run's model, rebuilt from the run's config.

    counts = {}
    param_count(run.cfg, counts)        # trainable parameters (actor and critic); counts: memo over configurations
"""
from __future__ import annotations

import json
from pathlib import Path

import yaml
from omegaconf import OmegaConf

from ..nets import model_from_config

CONF = Path(__file__).resolve().parents[2] / "experiments" / "conf"


def param_count(cfg: dict, memo: dict[str, int] | None = None) -> int:
    """Trainable parameters of a run's model (mjx_morph.nets.model_from_config + Model.num_params, traced with
    jax.eval_shape), from its resolved config over the defaults of experiments/conf/{arch,env}/<name>.yaml.
    `memo` (the caller's) maps each configuration counted to its count, so that a configuration is built once."""
    def conf_yaml(group: str, name: str) -> dict:
        f = CONF / group / f"{name}.yaml"
        try:
            d = yaml.safe_load(f.read_text()) if f.is_file() else {}
        except yaml.YAMLError:
            d = {}
        return d if isinstance(d, dict) else {}

    arch, env = dict(cfg.get("arch") or {}), dict(cfg.get("env") or {})
    arch_full = {**conf_yaml("arch", str(arch.get("name"))), **arch}
    arch_full["model"] = {**(conf_yaml("arch", str(arch.get("name"))).get("model") or {}),
                          **(arch.get("model") or {})}
    env_full = {**conf_yaml("env", str(env.get("name"))), **env}
    env_full = {"hfield_obs": bool(env_full.get("hfield_obs", False)),
                "decoder_dims": list(env_full.get("decoder_dims") or [])}
    overrides = dict(cfg.get("model_overrides") or {})
    key = json.dumps([arch_full, env_full, overrides], sort_keys=True, default=str)
    memo = {} if memo is None else memo
    if key not in memo:
        model = model_from_config(OmegaConf.create(arch_full), OmegaConf.create(env_full), **overrides)
        memo[key] = model.num_params()
    return memo[key]
