"""Here, after a lease: what its calls brought back, into results/ (through `bash tools/device_job.sh home`).

    bash tools/device_job.sh home results/<study>_s<session> <files_at> [<files_at> ...]   # the calls, in order

- the runs: every call packs the small artefacts of all the runs on its machine (`<name>-runs.tar.gz`), so the last
  call that brought any holds them whole; they land in the results folder (a study's `<study>/<run>` as
  `<folder>/<run>`; several studies' runs, or runs outside a study, under their own names), except those that
  stopped short of the iteration their config ends them at (a run to be moved or continued by a later lease):
  named and left out, so that no report reads a partial run as finished; and those already on file elsewhere in
  the results folder's parent (the same name and metrics.csv: a run a lease only evaluated, or one packed beside
  another): not brought twice, their evaluations that the copy on file lacks added to it;
- each call's log (`<name>.log`) as `call<k>.log` (k: the call's place in the order given);
- the newest compilation cache (`xla-cache.tar.gz`) into .gpu/, where the next lease's first call starts from it
  (device_job.sh then fits it to the room the checkout leaves); the programs of the archive it replaces go to the
  front of the overflow, .xla/xla-cache.tar.gz (tools/xla_cache.py), so that none is lost before `fit` chooses;
- then the runs' "Returns (main runs)", "Rates per phase" and "Health" tables, from a report built in a temporary
  folder (the evaluations' means, normalised, with their CIs over robots: what a lease's notes quote).

The results folder must not exist yet: results already on file are never overwritten. A run moved to the next
lease comes home with the lease that finishes it; parts of a moved run among the calls' files are named, with the
`stage` command that keeps them for the next lease (tools/move_runs.py).
"""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from xla_cache import merge      # tools/ (this script's folder) is on the path


def bring_home(dest: Path, calls: list[Path], gpu_dir: Path | None = Path(".gpu")) -> list[str]:
    """Copy the runs, the logs and the newest cache of `calls` (folders of the device tool's files, in the order the
    calls ran) as the module says; returns what was done, a line each. Raises SystemExit naming the problem."""
    from mjx_morph.eval.runs import read_run
    if dest.exists():
        raise SystemExit(f"{dest}: already exists; bring a lease home into a new folder (results/<study>_s<session>)")
    for c in calls:
        if not c.is_dir():
            raise SystemExit(f"{c}: not a folder of a call's files (the device tool's files_at)")
    tars = [t for c in calls for t in sorted(c.glob("*-runs.tar.gz"))]
    if not tars:
        raise SystemExit(f"no <name>-runs.tar.gz in {', '.join(map(str, calls))}: no run came back")
    done = []
    unfinished = []
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(tars[-1]) as tf:
            tf.extractall(tmp, filter="data")
        # runs short of their stop are left out; a run already on file (its name and metrics.csv the same, elsewhere
        # in the results root: a lease that only evaluated it, or packed it beside another run) is not brought twice,
        # and the evaluations its copy on file lacks join it there
        for run in sorted(p.parent for p in Path(tmp).rglob("config.yaml")):
            short = read_run(run).short_of_stop()
            kept = None if short else on_file(run, dest.parent)
            if short:
                unfinished.append(f"{run.relative_to(tmp)} (iteration {short[0]} of {short[1]})")
            elif kept is not None:
                added = [e for e in sorted((run / "eval").glob("*.json")) if not (kept / "eval" / e.name).exists()]
                for e in added:
                    (kept / "eval").mkdir(exist_ok=True)
                    shutil.copy(e, kept / "eval" / e.name)
                done.append(f"{run.relative_to(tmp)}: already on file at {kept}, not brought again"
                            + (f"; its new evaluations added there: {', '.join(e.name for e in added)}" if added else ""))
            else:
                continue
            drop(run, Path(tmp))
        # one study left (the others' runs all unfinished, session 67): its runs directly in the results folder
        tops = sorted(Path(tmp).iterdir())
        one_study = len(tops) == 1 and tops[0].is_dir() and not (tops[0] / "config.yaml").exists()
        shutil.copytree(tops[0] if one_study else Path(tmp), dest)
    runs = sorted(p.parent.relative_to(dest) for p in dest.rglob("config.yaml"))
    counted = f"{len(runs)} run" + ("" if len(runs) == 1 else "s")
    done.insert(0, f"{counted} from {tars[-1]} -> {dest}" + (f": {', '.join(map(str, runs))}" if runs else ""))
    if unfinished:
        done.append(f"left out, not finished (they come home with the lease that finishes them; to keep one as it is, "
                    f"take it from {tars[-1]}): {', '.join(unfinished)}")
    for k, c in enumerate(calls, 1):
        logs = sorted(c.glob("*.log"))
        for log in logs:
            name = f"call{k}.log" if len(logs) == 1 else f"call{k}-{log.name}"
            shutil.copy(log, dest / name)
            done.append(f"{log} -> {dest / name}")
    parts = [x for c in calls for x in c.glob("move.*.tar.gz.[0-9][0-9][0-9]")]
    if parts:      # the calls that hold parts (a later `send` call's, not given here, may hold the rest)
        holders = [str(c) for c in calls if any(x.parent == c for x in parts)]
        done.append(f"{len(parts)} parts of moved runs came too: stage them for the next lease with python3 "
                    f"tools/move_runs.py stage {' '.join(holders)} <the folders of any send calls after them> .mv")
    caches = [x for c in calls for x in c.glob("xla-cache.tar.gz")]
    if caches and gpu_dir is not None:
        gpu_dir.mkdir(exist_ok=True)
        if (gpu_dir / "xla-cache.tar.gz").is_file():
            overflow = gpu_dir.with_name(".xla") / "xla-cache.tar.gz"
            n = merge(gpu_dir / "xla-cache.tar.gz", overflow)
            done.append(f"{gpu_dir / 'xla-cache.tar.gz'}'s programs to the front of {overflow} ({n} in all)")
        shutil.copy(caches[-1], gpu_dir / "xla-cache.tar.gz")
        done.append(f"{caches[-1]} -> {gpu_dir / 'xla-cache.tar.gz'}")
    return done


def drop(run: Path, top: Path) -> None:
    """Remove `run` and the folders above it, up to `top`, that held nothing else (a study's of this run alone)."""
    shutil.rmtree(run)
    for parent in run.parents:
        if parent == top or any(parent.iterdir()):
            break
        parent.rmdir()


def on_file(run: Path, root: Path) -> Path | None:
    """The run directory under `root` (results/) that holds `run` already: the same name and metrics.csv."""
    if not root.is_dir() or not (run / "metrics.csv").exists():
        return None
    metrics = (run / "metrics.csv").read_bytes()
    for m in sorted(root.rglob(f"{run.name}/metrics.csv")):
        if m.read_bytes() == metrics:
            return m.parent
    return None


def report_tables(dest: Path, titles=("Returns (main runs)", "Rates per phase", "Health")) -> str:
    """The named tables of a report over the runs of `dest` (built in a temporary folder), as markdown."""
    with tempfile.TemporaryDirectory() as tmp:
        p = subprocess.run([sys.executable, "-m", "experiments.report", f"runs=[{dest}]", f"out={tmp}"],
                           capture_output=True, text=True)
        if p.returncode:
            return f"(the report failed: {p.stderr.strip().splitlines()[-1] if p.stderr.strip() else p.returncode})"
        md = (Path(tmp) / "report.md").read_text()
    parts = re.split(r"(?m)^(?=##+ )", md)
    return "\n".join(s.rstrip() + "\n" for s in parts if any(s.startswith(f"### {t}\n") for t in titles))


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        raise SystemExit("usage: bash tools/device_job.sh home <results folder> <files_at> [<files_at> ...]")
    dest = Path(argv[0])
    for line in bring_home(dest, [Path(a) for a in argv[1:]]):
        print(f"[home] {line}")
    if any(dest.rglob("config.yaml")):
        print(report_tables(dest))


if __name__ == "__main__":
    main(sys.argv[1:])
