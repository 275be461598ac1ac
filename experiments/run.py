"""Train a policy: `python -m experiments.run env=<ft|incline|csr|obstacle> arch=<name> [key=value ...]`.

    python -m experiments.run env=incline arch=rmomo                 # the GPU default preset
    python -m experiments.run preset=smoke                            # 2 robots, tiny nets, a few CPU minutes
    python -m experiments.run preset=paper seed=1 total_steps=200000000
    python -m experiments.run robots=unimal100/train num_robots=25 run_dir=runs/size25
    python -m experiments.run ppo.kl_threshold=0.03 model.d_model=64 env.self_collision=true

Rerunning with the same run_dir resumes from its newest checkpoint. Every key, its type and its default:
mjx_morph/run/config.py (`--help` prints them); unknown keys and wrong types are errors.
"""
from __future__ import annotations

import sys

from mjx_morph.run import RunConfig, train

from . import cli

def main(argv=None) -> int:
    return cli.main(train, "config", RunConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
