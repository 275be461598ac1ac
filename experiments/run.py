"""Train a policy: `python -m experiments.run env=<ft|incline|csr|obstacle> arch=<name> [overrides]`.

    python -m experiments.run env=incline arch=rmomo                 # the GPU default preset
    python -m experiments.run preset=smoke                            # 2 robots, tiny nets, a few CPU minutes
    python -m experiments.run preset=paper seed=1 total_steps=200000000
    python -m experiments.run robots=unimal100/train num_robots=25 run_dir=runs/size25

Rerunning with the same run_dir resumes from its newest checkpoint. Unknown keys are errors (Hydra struct mode).
Configs: experiments/conf/{config.yaml, env/, arch/, preset/}.
"""
from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from mjx_morph.ppo.loop import train, use_compile_cache
from mjx_morph.ppo.run_dir import RunDirError
from mjx_morph.unimal.errors import RobotError


@hydra.main(config_path="conf", config_name="config", version_base=None)
def main(cfg: DictConfig) -> None:
    try:
        use_compile_cache(cfg.get("compile_cache"))
        train(cfg)
    except (RunDirError, RobotError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
