"""Bring runs home: the small artefacts of run directories, without checkpoints, TensorBoard or videos; or, with
`checkpoint=true`, everything an unfinished run needs to go on training on another machine.

    python -m experiments.collect runs=[runs/studies/ab_rmomo_cell] out=$OUT/ab_rmomo_cell.tar.gz   # GPU machine
    tar xzf ab_rmomo_cell.tar.gz -C results/                   # here: results/ab_rmomo_cell/<run dir>/...
    python -m experiments.collect runs=[runs/studies/ab_rmomo_cell] out=results/ab_rmomo_cell        # a folder

Moving an unfinished run (machines lent for 30 minutes, files that travel limited to 16 MiB each):

    python -m experiments.collect runs=[runs/studies/ab_precision] out=runs/moving/ab_precision.tar.gz \
        checkpoint=true part_mb=15        # ab_precision.tar.gz.000, .001, ...: each part at most 15 MiB
    cat ab_precision.tar.gz.* | tar xzf - -C runs/studies      # on the next machine, then rerun the study: it resumes

`checkpoint=true` adds each run directory's newest checkpoint (the whole train state: parameters, optimiser,
environments, recurrent state; an R-MoMo seed of the default geometry is 174 MB in memory, 106 MB as Orbax writes
it, and gzip gains nothing on it: 8 parts of 15 MiB) and its TensorBoard events; older checkpoints stay behind.
The resumed run continues exactly as if never moved.

Of each run directory found under `runs` (as experiments.report finds them), ARTEFACTS are kept: the resolved config,
its history, the devices of each invocation (devices.yaml), metrics.csv, eval/*.json and, for a run stopped because
it started broken, unhealthy.txt (figures are rebuilt by experiments.report). A folder of `runs` becomes one folder
of the output named as it (`runs/studies/ab_rmomo_cell/ft-rmomo-default-s0` -> `ab_rmomo_cell/ft-rmomo-default-s0`);
a run directory named directly keeps its own name. `out` ending in .tar.gz writes an archive, else a folder. A file
over `max_file_mb` is left out and named (the results stay committable); experiments.report rebuilds from what is
kept.
"""
from __future__ import annotations

import dataclasses
import io
import shutil
import sys
import tarfile
from pathlib import Path
from typing import Any, Optional

from omegaconf import MISSING

from mjx_morph.eval.runs import find_run_dirs
from mjx_morph.run import register

from . import cli

#: what a run directory keeps, relative to it (glob patterns)
ARTEFACTS = ("config.yaml", "config_history.yaml", "devices.yaml", "metrics.csv", "eval/*.json", "unhealthy.txt")


@dataclasses.dataclass
class CollectConfig:
    runs: Any = MISSING          # run directories or folders holding run directories
    out: str = MISSING           # <name>.tar.gz (an archive) or a folder
    max_file_mb: float = 2.0     # larger artefacts are left out (and named); checkpoints are never left out
    checkpoint: bool = False     # also the newest checkpoint and TensorBoard events: to resume the runs elsewhere
    part_mb: Optional[float] = None   # an archive cut into parts of at most this many MiB (<out>.000, .001, ...)


register("collect_schema", CollectConfig)


def newest_checkpoint(run_dir: Path) -> list[Path]:
    """The files of a run directory's newest checkpoint (checkpoints/<iteration>/...; [] if it has none)."""
    steps = [p for p in (run_dir / "checkpoints").glob("*") if p.is_dir() and p.name.isdigit()]
    if not steps:
        return []
    newest = max(steps, key=lambda p: int(p.name))
    return sorted(f for f in newest.rglob("*") if f.is_file())


def artefacts(roots: list[str], checkpoint: bool = False) -> list[tuple[Path, str, bool]]:
    """[(file, its name in the output, whether it is an artefact)] of every run directory under `roots` (with
    `checkpoint`: its newest checkpoint and TensorBoard events too, which are not artefacts)."""
    kept = []
    for root in roots:
        root = Path(root)
        for d in find_run_dirs([root]):
            base = Path(root.name) / d.relative_to(root) if d != root else Path(d.name)
            files = [(f, True) for pattern in ARTEFACTS for f in sorted(d.glob(pattern))]
            if checkpoint:
                state = newest_checkpoint(d) + sorted(f for f in (d / "tb").glob("*") if f.is_file())
                files += [(f, False) for f in state]
            kept += [(f, str(base / f.relative_to(d)), artefact) for f, artefact in files]
    return kept


class Parts(io.RawIOBase):
    """A write-only stream cut into files of at most `size` bytes: <base>.000, <base>.001, ... (`cat` joins them)."""

    def __init__(self, base: Path, size: int):
        super().__init__()
        if size < 1:
            raise ValueError(f"part_mb: expected a positive size, got {size} bytes")
        self.base, self.size, self.paths = base, size, []
        self._f, self._left = None, 0

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        data = memoryview(b).cast("B")
        n = 0
        while n < len(data):
            if self._left == 0:
                if self._f is not None:
                    self._f.close()
                self.paths.append(self.base.with_name(f"{self.base.name}.{len(self.paths):03d}"))
                self._f, self._left = self.paths[-1].open("wb"), self.size
            k = min(self._left, len(data) - n)
            self._f.write(data[n:n + k])
            n, self._left = n + k, self._left - k
        return n

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None
        super().close()


def collect(c: CollectConfig) -> None:
    roots = [str(r) for r in (c.runs if isinstance(c.runs, (list, tuple)) else [c.runs])]
    archive = c.out.endswith((".tar.gz", ".tgz"))
    if c.part_mb is not None and not archive:
        raise ValueError(f"part_mb={c.part_mb}: parts are cut from an archive; expected out=<name>.tar.gz, "
                         f"got out={c.out}")
    limit = int(c.max_file_mb * 2 ** 20)
    found = artefacts(roots, c.checkpoint)
    files, left_out = [], []
    for f, name, artefact in found:
        if artefact and f.stat().st_size > limit:
            left_out.append(f"{f} ({f.stat().st_size / 2 ** 20:.2f} MB)")
        else:
            files.append((f, name))
    out = Path(c.out)
    if archive:
        out.parent.mkdir(parents=True, exist_ok=True)
        stream = Parts(out, int(c.part_mb * 2 ** 20)) if c.part_mb is not None else out.open("wb")
        with stream, tarfile.open(fileobj=stream, mode="w|gz") as tar:
            for f, name in files:
                tar.add(f, arcname=name)
        written = stream.paths if c.part_mb is not None else [out]
        if c.part_mb is not None:
            print(f"[mjx_morph] {len(written)} parts of at most {c.part_mb} MiB: {written[0].name} ... "
                  f"{written[-1].name}; join them with: cat {out.name}.* | tar xzf - -C <folder>")
    else:
        for f, name in files:
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, out / name)
        written = [out / name for _, name in files]
    runs = sum(1 for f, _, artefact in found if artefact and f.name == "config.yaml")   # one per run directory
    size = sum(f.stat().st_size for f, _ in files)
    written = sum(p.stat().st_size for p in written)
    print(f"[mjx_morph] {len(files)} files of {runs} run directories ({size / 2 ** 20:.2f} MB, "
          f"{written / 2 ** 20:.2f} MB written) -> {out}")
    for f in left_out:
        print(f"[mjx_morph] left out, over max_file_mb={c.max_file_mb}: {f}", file=sys.stderr)


def main(argv=None) -> int:
    return cli.main(collect, "collect_schema", CollectConfig, __doc__, argv)


if __name__ == "__main__":
    sys.exit(main())
