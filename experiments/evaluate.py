"""Zero-shot evaluation of a trained run: `python -m experiments.evaluate run_dir=<dir> robots=<set>`.

    python -m experiments.evaluate run_dir=runs/ft-rmomo-s0                      # train, test and variants
    python -m experiments.evaluate run_dir=runs/ft-rmomo-s0 robots=test episodes=8
    python -m experiments.evaluate run_dir=runs/ft-rmomo-s0 'robots=[val,unimal100/test]'

Results go to <run_dir>/eval/<set>.csv (one row per episode) and <set>.json (summary); see mjx_morph.eval.evaluate.
"""
from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from mjx_morph.eval.evaluate import evaluate_run
from mjx_morph.ppo.loop import use_compile_cache
from mjx_morph.ppo.run_dir import RunDirError
from mjx_morph.unimal.errors import RobotError


@hydra.main(config_path="conf", config_name="evaluate", version_base=None)
def main(cfg: DictConfig) -> None:
    c = OmegaConf.to_container(cfg, resolve=True)
    sets = c["robots"] if isinstance(c["robots"], list) else [c["robots"]]
    try:
        use_compile_cache(c.get("compile_cache"))
        evaluate_run(c["run_dir"], sets, episodes=int(c["episodes"]), seed=int(c["seed"]),
                     zero_state_steps=int(c["zero_state_steps"]), step=c["step"], max_envs=c["max_envs"],
                     episode_length=c["episode_length"], trace_steps=int(c["trace_steps"]))
    except (RunDirError, RobotError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
