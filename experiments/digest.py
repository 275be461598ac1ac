"""Which physics a run trained on, against what this checkout simulates for its config.

    python -m experiments.digest runs=[results/paper_s46]            # each run below: recorded vs this checkout
    python -m experiments.digest runs=[results/paper_s45/ft-rmemo-main-s7] \
        'record="trained at b9eec86; since then mjx_morph/sim only gained the digest"'   # physics.yaml

For each run directory at or below `runs`, builds the env its config trains on (task, robots, simulator options)
with this checkout's code and prints its model digest (`UnimalEnv.digest`: the stacked MJX model, the robots'
constants, the solver options, MuJoCo's and MJX's versions) beside the digest the run recorded while it trained
(devices.yaml, from session 45 on). Exit status 1 when a run recorded another: this checkout would not resume it
(the resume refuses, `allow_changes=[model_digest]` aside) and its new seeds would not share that run's physics.
Check before a lease that continues a comparison.

`record=WHY`: for runs that recorded no digest, write this checkout's into `physics.yaml` with the commit and WHY,
the reason the checkout's physics is the run's (free text goes in double quotes inside the shell's single quotes,
as above, so that Hydra reads punctuation as text): the report then shows the run's physics, marked as computed
(`d38de03b*`). Only true where the run's code and this checkout's build the same models (e.g. `git log
<run's commit>..HEAD -- mjx_morph/sim mjx_morph/unimal mjx_morph/layout.py` changes nothing they build); the
digest cannot check that for you. Runs that recorded one are never written to.

Envs are built once per distinct (task, robots, simulator options) and shared by the runs that have them.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path
from typing import List, Optional

from mjx_morph.eval.runs import find_run_dirs
from mjx_morph.run import read_run_config, register
from mjx_morph.run.build import make_env_for, train_robots
from mjx_morph.run.run_dir import read_computed_physics, recorded_digests, write_computed_physics

from . import cli


@dataclasses.dataclass
class DigestConfig:
    runs: List[str] = dataclasses.field(default_factory=list)   # run directories, or folders holding them
    record: Optional[str] = None        # why this checkout's physics is the runs': physics.yaml for those with none


register("digest_schema", DigestConfig)


def checkout_commit() -> str:
    """The commit of this checkout, with '+changes' where mjx_morph differs from it; 'unknown' outside git."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "mjx_morph"], cwd=root).returncode != 0
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("+changes" if dirty else "")


def env_digest(cfg, cache: dict) -> str:
    """The model digest of the env `cfg` (a RunConfig) trains on, built with this checkout's code."""
    key = (cfg.robots, cfg.robots_root, cfg.num_robots, cfg.allow_outside_design_space, repr(cfg.env))
    if key not in cache:
        _, robots = train_robots(cfg)
        cache[key] = make_env_for(cfg, robots).digest
    return cache[key]


def run(cfg: DigestConfig) -> int:
    if not cfg.runs:
        raise ValueError("runs=[...]: name the run directories (or folders holding them) to check")
    dirs = find_run_dirs(cfg.runs)
    if not dirs:
        raise FileNotFoundError(f"runs={list(cfg.runs)}: no run directory (with config.yaml) there")
    code, cache, differ = checkout_commit(), {}, 0
    for d in dirs:
        try:
            recorded, computed = recorded_digests(d), read_computed_physics(d)
        except ValueError as e:
            raise ValueError(f"{d}: {e}") from None
        now = env_digest(read_run_config(d / "config.yaml"), cache)
        if recorded:
            same = recorded[-1] == now
            differ += not same
            told = (f"recorded {' -> '.join(recorded)}; this checkout {now}: "
                    + ("the same physics" if same else "OTHER PHYSICS (it would not resume this run)"))
        elif computed:
            same = computed["model_digest"] == now
            differ += not same
            told = (f"computed {computed['model_digest']} (physics.yaml, {computed.get('code', '?')}); this "
                    f"checkout {now}: " + ("the same" if same else "OTHER PHYSICS"))
        elif cfg.record is not None:
            write_computed_physics(d, now, cfg.record, code)
            told = f"recorded none; this checkout {now}: written to {d / 'physics.yaml'}"
        else:
            told = f"recorded none; this checkout {now} (record=WHY writes it to physics.yaml)"
        print(f"{d}: {told}", flush=True)
    if differ:
        print(f"[digest] {differ} of {len(dirs)} runs trained on other physics than this checkout builds",
              file=sys.stderr)
    return 1 if differ else 0


def main(argv=None) -> int:
    status = []
    code = cli.main(lambda c: status.append(run(c)), "digest_schema", DigestConfig, __doc__, argv)
    return code or (status[0] if status else 0)


if __name__ == "__main__":
    sys.exit(main())
