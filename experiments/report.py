"""Figures, tables and a markdown report from finished runs: `python -m experiments.report runs=[...] out=<dir>`.

    python -m experiments.report runs=[runs/ft-rmomo-s0,runs/ft-modumorph-s0] out=reports/ft
    python -m experiments.report runs=[runs/studies/train_size] out=reports/size      # a folder of run dirs
    python -m experiments.report runs=[runs] out=reports/all 'compare=[rmomo,metamorph]'

Writes <out>/report.md with learning curves, zero-shot returns (train/test/variants), per-robot differences,
reward per timestep, training-set-size and single-context-feature figures (PNG) and tables (also as CSV); what
could not be drawn is listed under "Missing". See mjx_morph.eval.report.
"""
from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from mjx_morph.eval.report import build_report
from mjx_morph.eval.runs import NotARunDir, find_run_dirs


@hydra.main(config_path="conf", config_name="report", version_base=None)
def main(cfg: DictConfig) -> None:
    c = OmegaConf.to_container(cfg, resolve=True)
    runs = c["runs"] if isinstance(c["runs"], list) else [c["runs"]]
    compare = c.get("compare") or []
    compare = compare if isinstance(compare, list) else [compare]
    try:
        dirs = find_run_dirs(str(r) for r in runs)
    except NotARunDir as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    if not dirs:
        print("error: no run directories given", file=sys.stderr)
        sys.exit(2)
    path = build_report(dirs, c["out"], compare=[str(x) for x in compare],
                        title=str(c.get("title") or "mjx_morph report"))
    print(f"[mjx_morph] report: {path} ({len(dirs)} runs)")


if __name__ == "__main__":
    main()
