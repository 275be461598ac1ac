"""Move an unfinished run from one lent GPU machine to the next, across sessions (tools/device_job.sh).

A one-GPU lease trains one run of ~18 M steps with its evaluations (~1300-1400 s of its 1800) and the rest bought
nothing. With a move, the rest starts the next run: the lease's last call trains it until its limit, and
`DEVICE_JOB_MOVE_OUT=<run dir>` packs the run's newest checkpoint into 15-MiB parts that come back with the call
(`experiments.collect checkpoint=true`); here they wait in git-ignored folders of at most two parts each (`stage`),
the next lease's first calls carry one folder each onto the machine (`place`, ~30 MiB beside the ~27 MiB checkout
of the 64 MiB a call takes), and its training call puts the run back (`assemble`, in device_job.sh before the
command), whose study then resumes it exactly. Only feed-forward models fit: MetaMorph's whole train state is
41 MiB (3 parts), ModuMorph's 63 MiB (5, at the 64 MiB a call brings back), R-MeMo's 143 MiB and R-MoMo's 166 MiB
(their burn-in tails and recurrent states).

    python3 tools/move_runs.py name runs/studies/paper/ft-metamorph-main-s9     # move.paper.ft-metamorph-main-s9.tar.gz
    python3 tools/move_runs.py stage <files_at> .mv      # here: parts into .mv1/, .mv2/, ... (two each)
    python3 tools/move_runs.py place .mv1 moving         # there (device_job.sh place .mv1): kept on the machine
    python3 tools/move_runs.py assemble moving runs/studies     # there, before a command: the runs put back

Plain Python (no JAX): it runs before the wheels are installed.
"""
from __future__ import annotations

import io
import re
import shutil
import sys
import tarfile
from pathlib import Path

#: a part of a moved run: move.<study>.<run>.tar.gz.<3 digits> (study and run names hold no dots)
PART = re.compile(r"^move\.(?P<study>[A-Za-z0-9_-]+)\.(?P<run>[A-Za-z0-9_-]+)\.tar\.gz\.(?P<index>\d{3})$")
PARTS_PER_FOLDER = 2        # 2 x 15 MiB beside the checkout, within the 64 MiB a call carries


class MoveError(ValueError):
    pass


def archive_name(run_dir: str | Path) -> str:
    """The archive a run directory runs/studies/<study>/<run> moves in (experiments.collect's `out`)."""
    p = Path(run_dir)
    name = f"move.{p.parent.name}.{p.name}.tar.gz"
    if not PART.match(name + ".000"):
        raise MoveError(f"{run_dir}: expected runs/studies/<study>/<run> with names of letters, digits, _ and -")
    return name


def parts_in(folder: Path) -> dict[tuple[str, str], list[Path]]:
    """The parts in `folder` by (study, run), in order; MoveError where one's numbers are not 000, 001, ... without
    a gap (a lost part: the last one's loss only the archive's end can tell)."""
    found: dict[tuple[str, str], dict[int, Path]] = {}
    for p in sorted(folder.iterdir()) if folder.is_dir() else []:
        m = PART.match(p.name)
        if m:
            found.setdefault((m["study"], m["run"]), {})[int(m["index"])] = p
    out = {}
    for key, by_index in found.items():
        missing = sorted(set(range(max(by_index) + 1)) - set(by_index))
        if missing:
            raise MoveError(f"{folder}: move.{key[0]}.{key[1]}.tar.gz lacks part(s) "
                            f"{', '.join(f'{i:03d}' for i in missing)}; it cannot be put back")
        out[key] = [by_index[i] for i in sorted(by_index)]
    return out


def stage(source: Path, prefix: str) -> list[Path]:
    """Copy the parts of `source` (a call's files) into folders <prefix>1, <prefix>2, ... of at most
    PARTS_PER_FOLDER parts each, one folder per call that carries them; returns the folders."""
    parts = [p for ps in parts_in(source).values() for p in ps]
    if not parts:
        raise MoveError(f"{source}: no parts of a moved run (move.<study>.<run>.tar.gz.NNN)")
    folders = []
    for i in range(0, len(parts), PARTS_PER_FOLDER):
        folder = Path(f"{prefix}{len(folders) + 1}")
        if folder.exists():
            raise MoveError(f"{folder} exists: place or remove the parts staged before")
        folder.mkdir(parents=True)
        for p in parts[i:i + PARTS_PER_FOLDER]:
            shutil.copyfile(p, folder / p.name)
        folders.append(folder)
    return folders


def place(folder: Path, moving: Path) -> int:
    """Copy the parts a call carried (`folder`) into `moving`, which stays on the machine between calls; returns
    how many."""
    parts = [p for p in sorted(folder.iterdir()) if PART.match(p.name)] if folder.is_dir() else []
    if not parts:
        raise MoveError(f"{folder}: no parts of a moved run here (carry the folder `stage` wrote)")
    moving.mkdir(parents=True, exist_ok=True)
    for p in parts:
        shutil.copyfile(p, moving / p.name)
    return len(parts)


def assemble(moving: Path, studies: Path) -> list[Path]:
    """Put every moved run of `moving` back as <studies>/<study>/<run> and remove its parts; returns the runs. A run
    whose parts are incomplete or corrupt, which holds anything but <run>/..., or whose directory exists already,
    raises MoveError naming it, and nothing of it is written."""
    done = []
    for (study, run), parts in parts_in(moving).items():
        target = studies / study / run
        label = f"{moving}/move.{study}.{run}.tar.gz.000-{len(parts) - 1:03d}"
        if target.exists():
            raise MoveError(f"{label}: {target} exists already; the moved run would replace it")
        tmp = studies / study / f".{run}.moving"      # extracted here first: a failure leaves nothing of the run
        shutil.rmtree(tmp, ignore_errors=True)
        stream = io.BytesIO(b"".join(p.read_bytes() for p in parts))
        try:
            try:
                with tarfile.open(fileobj=stream, mode="r:gz") as tar:
                    members = tar.getmembers()
                    strays = [m.name for m in members if m.name.split("/", 1)[0] != run
                              or ".." in m.name.split("/") or not (m.isfile() or m.isdir())]
                    if strays or not members:
                        raise MoveError(f"{label}: expected the files of {run}/ only, found {strays[:3] or 'nothing'}")
                    # the data filter where this Python has it (3.11.4+); the check above keeps to <run>/ either way
                    tar.extractall(tmp, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
            except (tarfile.TarError, EOFError, OSError) as e:
                raise MoveError(f"{label}: incomplete or corrupt ({type(e).__name__}: {e}); a lost last part looks "
                                "so") from None
            (tmp / run).rename(target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        for p in parts:
            p.unlink()
        done.append(target)
    return done


def main(argv: list[str]) -> int:
    try:
        if len(argv) == 2 and argv[0] == "name":
            print(archive_name(argv[1]))
        elif len(argv) == 3 and argv[0] == "stage":
            for folder in stage(Path(argv[1]), argv[2]):
                mib = sum(p.stat().st_size for p in folder.iterdir()) / 2 ** 20
                print(f"[move_runs] {folder}: {len(list(folder.iterdir()))} parts, {mib:.1f} MiB: carry it in one call"
                      f" (carry: [\"{folder}\"]) of `bash tools/device_job.sh place {folder}`")
        elif len(argv) == 3 and argv[0] == "place":
            n = place(Path(argv[1]), Path(argv[2]))
            kept = sorted(p.name for p in Path(argv[2]).iterdir())
            print(f"[move_runs] {n} part(s) of {argv[1]} kept in {argv[2]}, which holds {', '.join(kept)}")
        elif len(argv) == 3 and argv[0] == "assemble":
            for run in assemble(Path(argv[1]), Path(argv[2])):
                print(f"[move_runs] moved in: {run} (its study resumes it)")
        else:
            print(__doc__.split("\n\n")[2], file=sys.stderr)
            print("usage: move_runs.py name <run dir> | stage <folder> <prefix> | place <folder> <moving> | "
                  "assemble <moving> <studies>", file=sys.stderr)
            return 2
    except MoveError as e:
        print(f"[move_runs] error: {e}", file=sys.stderr)
        return 4
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
