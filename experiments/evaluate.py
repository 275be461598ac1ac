"""Zero-shot evaluation of a trained run: `python -m experiments.evaluate run_dir=<dir> [robots=<set or list>]`.

    python -m experiments.evaluate run_dir=runs/ft-rmomo-s0                      # train, test and variants
    python -m experiments.evaluate run_dir=runs/ft-rmomo-s0 robots=test episodes=8
    python -m experiments.evaluate run_dir=runs/ft-rmomo-s0 'robots=[val,unimal100/test]'

Results go to <run_dir>/eval/<set>.csv (one row per episode) and <set>.json (summary); see mjx_morph.eval.evaluate.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Any, List, Optional

from omegaconf import MISSING

from mjx_morph.eval.evaluate import evaluate_run
from mjx_morph.run import DEFAULT_COMPILE_CACHE, register

from . import cli


@dataclasses.dataclass
class EvaluateConfig:
    run_dir: str = MISSING              # a run directory of experiments.run
    robots: Any = dataclasses.field(default_factory=lambda: ["train", "test", "variants"])
                                        # a set or a list: train | val | test | variants[/<change>] | any set or path
    episodes: int = 4                   # episodes per robot (episode k of robot r always has the same key)
    seed: int = 0
    step: Optional[int] = None          # checkpoint (iteration) to evaluate; None: the newest
    zero_state_steps: int = 100         # recurrent models: also sweep with the state held at zero this many steps,
    zero_state_sets: List[str] = dataclasses.field(default_factory=lambda: ["test"])   # on the sets of these tags
    trace_steps: int = 500              # the reward of each of the first N steps is kept (reward per timestep)
    episode_length: Optional[int] = None   # None: the run's
    max_envs: Optional[int] = None      # episodes per jitted call (None: a whole set, in equal chunks of at most
                                        # evaluate.MAX_CHUNK, CPU_CHUNK on a CPU)
    compile_cache: Optional[str] = DEFAULT_COMPILE_CACHE


register("evaluate_schema", EvaluateConfig)


def run(c: EvaluateConfig) -> None:
    sets = c.robots if isinstance(c.robots, (list, tuple)) else [c.robots]
    evaluate_run(c.run_dir, [str(s) for s in sets], episodes=c.episodes, seed=c.seed,
                 zero_state_steps=c.zero_state_steps, zero_state_sets=c.zero_state_sets, step=c.step,
                 max_envs=c.max_envs, episode_length=c.episode_length, trace_steps=c.trace_steps)


def main(argv=None) -> int:
    return cli.main(run, "evaluate_schema", EvaluateConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
