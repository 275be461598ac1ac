"""Run a study: every run of experiments/conf/study/<name>.yaml for each architecture and seed, then evaluate it.

    python -m experiments.study train_size --archs rmomo modumorph --seeds 0 1 2 --env ft
    python -m experiments.study context_features --archs rmomo --dry-run          # list the runs only
    python -m experiments.study train_size --archs rmomo -- preset=smoke robots=gen/train   # extra overrides

Run directories: <out>/<study>/<env>-<arch>-<run>-s<seed> (default out: runs/studies). Each run is an ordinary
`experiments.run` run: rerunning the study resumes unfinished runs (finished ones are not retrained; their
evaluation runs again).
Afterwards: python -m experiments.report runs=[<out>/<study>] out=<dir>.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

CONF = Path(__file__).resolve().parent / "conf"


def plan(study: str, archs, seeds, env: str, out: Path, extra=()) -> list[tuple[Path, list[str], list[str]]]:
    """[(run dir, experiments.run overrides, sets to evaluate)] of a study."""
    f = CONF / "study" / f"{study}.yaml"
    if not f.exists():
        known = sorted(p.stem for p in (CONF / "study").glob("*.yaml"))
        raise SystemExit(f"error: no study {study!r} ({f} does not exist); known: {', '.join(known)}")
    spec = yaml.safe_load(f.read_text())
    runs = []
    for arch in archs:
        for seed in seeds:
            for name, overrides in spec["runs"].items():
                d = out / study / f"{env}-{arch}-{name}-s{seed}"
                runs.append((d, [f"env={env}", f"arch={arch}", f"seed={seed}", f"run_dir={d}", *overrides, *extra],
                             list(spec.get("evaluate", ["train", "test"]))))
    return runs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("study")
    p.add_argument("--archs", nargs="+", default=["rmomo", "modumorph"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--env", default="ft")
    p.add_argument("--out", type=Path, default=Path("runs/studies"))
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--dry-run", action="store_true", help="print the runs and exit")
    p.add_argument("overrides", nargs="*", help="extra experiments.run overrides (after --)")
    a = p.parse_args(argv)
    runs = plan(a.study, a.archs, a.seeds, a.env, a.out, a.overrides)
    for d, ov, sets in runs:
        print(f"python -m experiments.run {' '.join(ov)}   # then evaluate {sets}")
    if a.dry_run:
        return 0
    from hydra import compose, initialize_config_dir

    from mjx_morph.eval.evaluate import evaluate_run
    from mjx_morph.ppo.loop import train, use_compile_cache
    for i, (d, ov, sets) in enumerate(runs):
        print(f"[study] {i + 1}/{len(runs)}: {d}", flush=True)
        with initialize_config_dir(config_dir=str(CONF), version_base=None):
            cfg = compose(config_name="config", overrides=ov)
        if i == 0:
            use_compile_cache(cfg.get("compile_cache"))
        train(cfg)
        evaluate_run(d, sets, episodes=a.episodes)
    print(f"[study] done; report: python -m experiments.report runs=[{a.out / a.study}] out=<dir>")
    return 0


if __name__ == "__main__":
    sys.exit(main())
