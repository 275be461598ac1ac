"""Move an unfinished run from one lent GPU machine to the next, across sessions (tools/device_job.sh).

A one-GPU lease trains one run of ~18 M steps with its evaluations (~1300-1400 s of its 1800) and the rest bought
nothing; a run of the paper's 100 M steps outlasts any lease. With a move, a run goes on in the next session: a
lease's last call trains it until its limit, and `DEVICE_JOB_MOVE_OUT=<run dir>` packs the run's newest checkpoint
into 15-MiB parts in outgoing/ on the machine (`experiments.collect checkpoint=true`) and sends what fits of them
back with the call (`send`: a call brings back at most 8 files and 64 MiB); each later call of
`bash tools/device_job.sh send` sends the next four. Here they wait in git-ignored folders of at most two parts
each (`stage`, which first checks that each run's parts are all there), the next lease's first calls carry one
folder each onto the machine (`place`, ~30 MiB beside the ~25 MiB checkout of the 64 MiB a call takes), and its
training call puts the run back (`assemble`, in device_job.sh before the command), whose study then resumes it
exactly. Whole train states, packed: MetaMorph 36 MiB (3 parts), R-MeMo 86 MiB (6; 143 unpacked, its burn-in tail
and recurrent states); unpacked, ModuMorph 63 MiB (at most 5) and R-MoMo 166 MiB (at most 12): a move out takes the
packing call and up to three `send` calls, a move in one `place` call per two parts.

    python3 tools/move_runs.py name runs/studies/paper/ft-metamorph-main-s9     # move.paper.ft-metamorph-main-s9.tar.gz
    python3 tools/move_runs.py send outgoing $OUT        # there: the next parts that fit into $OUT, the rest kept
    python3 tools/move_runs.py stage <files_at> [<files_at> ...] .mv      # here: parts into .mv1/, .mv2/ (two each)
    python3 tools/move_runs.py place .mv1 moving         # there (device_job.sh place .mv1): kept on the machine
    python3 tools/move_runs.py assemble moving runs/studies     # there, before a command: the runs put back
                                    # (parts of a run the machine still holds at their checkpoint or later dropped)

Plain Python (no JAX): it runs before the wheels are installed.
"""
from __future__ import annotations

import io
import re
import shutil
import sys
import tarfile
import zlib
from pathlib import Path

#: a part of a moved run: move.<study>.<run>.tar.gz.<3 digits> (study and run names hold no dots)
PART = re.compile(r"^move\.(?P<study>[A-Za-z0-9_-]+)\.(?P<run>[A-Za-z0-9_-]+)\.tar\.gz\.(?P<index>\d{3})$")
PARTS_PER_FOLDER = 2        # 2 x 15 MiB beside the checkout, within the 64 MiB a call carries
#: what one call brings back from $OUT (the device tool's limits), less a margin of 1 MiB
OUT_MIB, OUT_FILES, OUT_MARGIN_MIB = 64.0, 8, 1.0


class MoveError(ValueError):
    pass


def part_key(p: Path) -> tuple[str, str, int] | None:
    """(study, run, index) of a part's file name; None for any other file."""
    m = PART.match(p.name)
    return (m["study"], m["run"], int(m["index"])) if m else None


def archive_name(run_dir: str | Path) -> str:
    """The archive a run directory runs/studies/<study>/<run> moves in (experiments.collect's `out`)."""
    p = Path(run_dir)
    name = f"move.{p.parent.name}.{p.name}.tar.gz"
    if not PART.match(name + ".000"):
        raise MoveError(f"{run_dir}: expected runs/studies/<study>/<run> with names of letters, digits, _ and -")
    return name


def parts_in(folder: Path | list[Path]) -> dict[tuple[str, str], list[Path]]:
    """The parts in `folder` (or in several folders) by (study, run), in order; MoveError where one's numbers are
    not 000, 001, ... without a gap (a lost part: the last one's loss only the archive's end can tell,
    `check_complete`), or where one part is in two folders with other bytes."""
    folders = folder if isinstance(folder, list) else [folder]
    found: dict[tuple[str, str], dict[int, Path]] = {}
    for f in folders:
        for p in sorted(f.iterdir()) if f.is_dir() else []:
            key = part_key(p)
            if key is None:
                continue
            seen = found.setdefault(key[:2], {}).setdefault(key[2], p)
            if seen != p and seen.read_bytes() != p.read_bytes():
                raise MoveError(f"{p.name}: in {seen.parent} and {f} with other bytes; which one came back whole "
                                "cannot be told")
    out = {}
    for key, by_index in found.items():
        missing = sorted(set(range(max(by_index) + 1)) - set(by_index))
        if missing:
            raise MoveError(f"{', '.join(map(str, folders))}: move.{key[0]}.{key[1]}.tar.gz lacks part(s) "
                            f"{', '.join(f'{i:03d}' for i in missing)}; it cannot be put back")
        out[key] = [by_index[i] for i in sorted(by_index)]
    return out


def send(outgoing: Path, out: Path, room_mib: float | None = None, files: int | None = None
         ) -> tuple[list[Path], list[Path]]:
    """Move the parts waiting in `outgoing` (on the GPU machine) into `out` ($OUT), in order, while they fit beside
    what `out` holds already within `room_mib` MiB and `files` files, by default what a call brings back (OUT_MIB
    less a margin, OUT_FILES). Returns (sent, left)."""
    # in order, without parts_in's gap check: the parts sent before are gone from `outgoing`
    waiting = sorted((p for p in outgoing.iterdir() if part_key(p)), key=part_key) if outgoing.is_dir() else []
    there = [p for p in out.rglob("*") if p.is_file()] if out.is_dir() else []
    room_mib = OUT_MIB - OUT_MARGIN_MIB if room_mib is None else room_mib
    room = room_mib * 2 ** 20 - sum(p.stat().st_size for p in there)
    slots = (OUT_FILES if files is None else files) - len(there)
    sent = []
    for p in waiting:
        size = p.stat().st_size
        if size > room or slots < 1:
            break                       # in order: a later part never goes before an earlier one
        out.mkdir(parents=True, exist_ok=True)
        shutil.move(str(p), out / p.name)
        sent.append(out / p.name)
        room, slots = room - size, slots - 1
    return sent, waiting[len(sent):]


#: what reading a truncated or corrupt archive raises
READ_ERRORS = (tarfile.TarError, EOFError, OSError, zlib.error)


def open_parts(parts: list[Path]) -> tarfile.TarFile:
    """A run's parts, in order, read as the one archive they were cut from."""
    return tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in parts)), mode="r:gz")


def check_complete(key: tuple[str, str], parts: list[Path]) -> None:
    """Read a run's parts through to the archive's end: MoveError where one is missing or corrupt (the last one's
    loss shows only there)."""
    try:
        with open_parts(parts) as tar:
            for _ in tar:
                pass
    except READ_ERRORS as e:
        raise MoveError(f"move.{key[0]}.{key[1]}.tar.gz: its {len(parts)} part(s) here end before the archive does "
                        f"({type(e).__name__}): a part is missing or corrupt. The last ones may still wait on the "
                        "machine that packed them (bash tools/device_job.sh send); nothing was staged") from None


def stage(sources: Path | list[Path], prefix: str) -> list[Path]:
    """Copy the parts of `sources` (the files of the calls that brought them back) into folders <prefix>1,
    <prefix>2, ... of at most PARTS_PER_FOLDER parts each, one folder per call that carries them; returns the
    folders. Each run's parts must be all there (`parts_in`, `check_complete`); else MoveError, and nothing is
    staged."""
    sources = [sources] if isinstance(sources, Path) else list(sources)
    for source in sources:
        if not source.is_dir():
            raise MoveError(f"{source}: not a folder of a call's files")
    runs = parts_in(sources)
    if not runs:
        raise MoveError(f"{', '.join(map(str, sources))}: no parts of a moved run (move.<study>.<run>.tar.gz.NNN)")
    for key, ps in runs.items():
        check_complete(key, ps)
    parts = [p for ps in runs.values() for p in ps]
    folders = [Path(f"{prefix}{k + 1}") for k in range(-(-len(parts) // PARTS_PER_FOLDER))]
    for folder in folders:
        if folder.exists():
            raise MoveError(f"{folder} exists: place or remove the parts staged before; nothing was staged")
    for k, folder in enumerate(folders):
        folder.mkdir(parents=True)
        for p in parts[k * PARTS_PER_FOLDER:(k + 1) * PARTS_PER_FOLDER]:
            shutil.copyfile(p, folder / p.name)
    return folders


def place(folder: Path, moving: Path) -> int:
    """Copy the parts a call carried (`folder`) into `moving`, which stays on the machine between calls; returns
    how many."""
    parts = [p for p in sorted(folder.iterdir()) if part_key(p)] if folder.is_dir() else []
    if not parts:
        raise MoveError(f"{folder}: no parts of a moved run here (carry the folder `stage` wrote)")
    moving.mkdir(parents=True, exist_ok=True)
    for p in parts:
        shutil.copyfile(p, moving / p.name)
    return len(parts)


def newest_checkpoint(names) -> int:
    """The highest <N> of checkpoints/<N> among `names` (paths relative to the run); -1 for none."""
    steps = [int(parts[1]) for parts in (n.split("/") for n in names)
             if len(parts) > 1 and parts[0] == "checkpoints" and parts[1].isdigit()]
    return max(steps, default=-1)


def assemble(moving: Path, studies: Path) -> tuple[list[Path], list[str]]:
    """Put every moved run of `moving` back as <studies>/<study>/<run> and remove its parts; returns the runs put
    back, and a line for each run whose parts were dropped because the machine holds it already at their checkpoint
    or later (a warm machine keeps a run it moved out, session 89). A run whose parts are incomplete or corrupt,
    which holds anything but <run>/..., or whose directory exists at an older checkpoint (or none), raises MoveError
    naming it, and nothing of it is written."""
    done, dropped = [], []
    for (study, run), parts in parts_in(moving).items():
        target = studies / study / run
        label = f"{moving}/move.{study}.{run}.tar.gz.000-{len(parts) - 1:03d}"
        held_here = target.exists()
        tmp = studies / study / f".{run}.moving"      # extracted here first: a failure leaves nothing of the run
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            try:
                with open_parts(parts) as tar:
                    members = tar.getmembers()
                    strays = [m.name for m in members if m.name.split("/", 1)[0] != run
                              or ".." in m.name.split("/") or not (m.isfile() or m.isdir())]
                    if strays or not members:
                        raise MoveError(f"{label}: expected the files of {run}/ only, found {strays[:3] or 'nothing'}")
                    if held_here:
                        packed = newest_checkpoint(m.name.split("/", 1)[-1] for m in members)
                        held = newest_checkpoint(f"checkpoints/{p.name}" for p in (target / "checkpoints").glob("*"))
                        if not 0 <= packed <= held:
                            raise MoveError(f"{label}: {target} exists already (checkpoint {held}, the parts' "
                                            f"{packed}); the moved run would replace it")
                        dropped.append(f"{target} is here already at checkpoint {held} (this machine kept it after "
                                       f"moving it out), its {len(parts)} placed part(s) hold checkpoint {packed}: "
                                       "the parts were dropped")
                    else:
                        # the data filter where this Python has it (3.11.4+); the check above keeps to <run>/ anyway
                        tar.extractall(tmp, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
            except READ_ERRORS as e:
                raise MoveError(f"{label}: incomplete or corrupt ({type(e).__name__}: {e}); a lost last part looks "
                                "so") from None
            if not held_here:
                (tmp / run).rename(target)
                done.append(target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        for p in parts:
            p.unlink()
    return done, dropped


def main(argv: list[str]) -> int:
    try:
        if len(argv) == 2 and argv[0] == "name":
            print(archive_name(argv[1]))
        elif len(argv) >= 3 and argv[0] == "stage":
            for folder in stage([Path(a) for a in argv[1:-1]], argv[-1]):
                mib = sum(p.stat().st_size for p in folder.iterdir()) / 2 ** 20
                print(f"[move_runs] {folder}: {len(list(folder.iterdir()))} parts, {mib:.1f} MiB: carry it in one call"
                      f" (carry: [\"{folder}\"]) of `bash tools/device_job.sh place {folder}`")
        elif len(argv) in (3, 5) and argv[0] == "send":
            limits = (float(argv[3]), int(argv[4])) if len(argv) == 5 else ()
            sent, left = send(Path(argv[1]), Path(argv[2]), *limits)
            mib = sum(p.stat().st_size for p in sent) / 2 ** 20
            print(f"[move_runs] sent {len(sent)} part(s), {mib:.1f} MiB"
                  + (f": {sent[0].name} ... {sent[-1].name}" if sent else ""))
            if left:
                largest = max(p.stat().st_size for p in left)
                per_call = max(1, min(OUT_FILES, int((OUT_MIB - OUT_MARGIN_MIB) * 2 ** 20 // largest)))
                calls = -(-len(left) // per_call)
                print(f"[move_runs] {len(left)} part(s) left in {argv[1]}/ on this machine: {calls} more call(s) of "
                      f"`bash tools/device_job.sh send` bring them back (up to {per_call} a call) before it goes back")
            else:
                print(f"[move_runs] no part left in {argv[1]}/")
        elif len(argv) == 3 and argv[0] == "place":
            n = place(Path(argv[1]), Path(argv[2]))
            kept = sorted(p.name for p in Path(argv[2]).iterdir())
            print(f"[move_runs] {n} part(s) of {argv[1]} kept in {argv[2]}, which holds {', '.join(kept)}")
        elif len(argv) == 3 and argv[0] == "assemble":
            done, dropped = assemble(Path(argv[1]), Path(argv[2]))
            for line in dropped:
                print(f"[move_runs] {line}")
            for run in done:
                print(f"[move_runs] moved in: {run} (its study resumes it)")
        else:
            print(__doc__.split("\n\n")[2], file=sys.stderr)
            print("usage: move_runs.py name <run dir> | send <outgoing> <out> [<room MiB> <files>] | "
                  "stage <folder> [<folder> ...] <prefix> | place <folder> <moving> | assemble <moving> <studies>",
                  file=sys.stderr)
            return 2
    except MoveError as e:
        print(f"[move_runs] error: {e}", file=sys.stderr)
        return 4
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
