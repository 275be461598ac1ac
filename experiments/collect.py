"""Bring finished runs home: the small artefacts of run directories, without checkpoints, TensorBoard or videos.

    python -m experiments.collect runs=[runs/studies/ab_rmomo_cell] out=$OUT/ab_rmomo_cell.tar.gz   # GPU machine
    tar xzf ab_rmomo_cell.tar.gz -C results/                   # here: results/ab_rmomo_cell/<run dir>/...
    python -m experiments.collect runs=[runs/studies/ab_rmomo_cell] out=results/ab_rmomo_cell        # a folder

Of each run directory found under `runs` (as experiments.report finds them), ARTEFACTS are kept: the resolved config,
its history, the devices of each invocation (devices.yaml), metrics.csv and eval/*.json (figures are rebuilt by
experiments.report). A folder of `runs` becomes one folder of the output named as it
(`runs/studies/ab_rmomo_cell/ft-rmomo-default-s0` -> `ab_rmomo_cell/ft-rmomo-default-s0`); a run directory named
directly keeps its own name. `out` ending in .tar.gz writes an archive, else a folder. A file over
`max_file_mb` is left out and named (the results stay committable); experiments.report rebuilds from what is kept.
"""
from __future__ import annotations

import dataclasses
import shutil
import sys
import tarfile
from pathlib import Path
from typing import Any

from omegaconf import MISSING

from mjx_morph.eval.runs import find_run_dirs
from mjx_morph.run import register

from . import cli

#: what a run directory keeps, relative to it (glob patterns)
ARTEFACTS = ("config.yaml", "config_history.yaml", "devices.yaml", "metrics.csv", "eval/*.json")


@dataclasses.dataclass
class CollectConfig:
    runs: Any = MISSING          # run directories or folders holding run directories
    out: str = MISSING           # <name>.tar.gz (an archive) or a folder
    max_file_mb: float = 2.0     # larger files are left out (and named)


register("collect_schema", CollectConfig)


def artefacts(roots: list[str]) -> list[tuple[Path, str]]:
    """[(file, its name in the output)] of every run directory under `roots`."""
    kept = []
    for root in roots:
        root = Path(root)
        for d in find_run_dirs([root]):
            base = Path(root.name) / d.relative_to(root) if d != root else Path(d.name)
            for pattern in ARTEFACTS:
                for f in sorted(d.glob(pattern)):
                    kept.append((f, str(base / f.relative_to(d))))
    return kept


def collect(c: CollectConfig) -> None:
    roots = [str(r) for r in (c.runs if isinstance(c.runs, (list, tuple)) else [c.runs])]
    files = artefacts(roots)
    limit = int(c.max_file_mb * 2 ** 20)
    left_out = [f"{f} ({f.stat().st_size / 2 ** 20:.2f} MB)" for f, _ in files if f.stat().st_size > limit]
    files = [(f, name) for f, name in files if f.stat().st_size <= limit]
    out = Path(c.out)
    if c.out.endswith((".tar.gz", ".tgz")):
        out.parent.mkdir(parents=True, exist_ok=True)
        with tarfile.open(out, "w:gz") as tar:
            for f, name in files:
                tar.add(f, arcname=name)
    else:
        for f, name in files:
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, out / name)
    runs = len({f.parent.parent if f.parent.name == "eval" else f.parent for f, _ in files})
    size = sum(f.stat().st_size for f, _ in files)
    print(f"[mjx_morph] {len(files)} files of {runs} run directories ({size / 2 ** 20:.2f} MB) -> {out}")
    for f in left_out:
        print(f"[mjx_morph] left out, over max_file_mb={c.max_file_mb}: {f}", file=sys.stderr)


def main(argv=None) -> int:
    return cli.main(collect, "collect_schema", CollectConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
