"""Carry JAX's persistent compilation cache from one lent GPU machine to the next (tools/device_job.sh).

    python3 tools/xla_cache.py pack <cache dir> <archive.tar.gz> [max MiB]    # this lease's programs first
    python3 tools/xla_cache.py unpack <archive.tar.gz> <cache dir>
    python3 tools/xla_cache.py fit <archive.tar.gz> [<overflow.tar.gz>] < <the other files that travel, NUL-separated>
                                    # here: keep its first programs within the room the other files leave, and
                                    # those that give way (and the overflow's own) in the overflow, within the room
                                    # of a call that carries the checkout and the overflow alone

A fresh machine compiles the train step for ~100-150 s in a lease's first call; the programs compiled in an earlier
lease serve it when they travel (`.gpu/xla-cache.tar.gz`, carried). JAX reads an entry only when its key matches: the
same program (the training code unchanged), JAX version, compiler options, GPU model, and the machine's platform
version (CUDA, driver) and device topology; other entries are ignored. A one-GPU host's cache missed on a 4-GPU host
in session 32 (each run's devices.yaml records these parts of the key; docs/benchmarks.md, "Session 32").
The training programs go first (the train step's rollout and update, and the initial state: each 40-70 s of compilation
that every GPU of a lease waits for before its first iteration), then the others (the evaluations' sweeps, ~2.4 MiB
each on a GPU, mostly compiled while the runs train); within each, what this lease compiled first, oldest first, then
what earlier leases brought, those read in this lease before the others (`pack`). Session 28 measured why: with this
lease's programs first whatever their kind, its four new sweeps (9.6 MiB) left room for one model's train step alone,
and the model it had read from the carried cache lost its own. Plain Python (no JAX): it runs before the wheels are
installed and after the command ended.

The room beside the checkout and the wheels holds two or three models' training programs (~5.2-5.7 MiB each on an
H100; 16.4 MiB of room since session 85's slimmer wheels, tools/slim_wheels.py), fewer than the model-topology pairs
of a lease that runs two models on whichever of two H100 hosts comes, and a miss costs ~60-110 s of compilation
(sessions 73-85). So what gives way is kept here too, in the overflow (`.xla/xla-cache.tar.gz`, with the programs of
the archive `home` replaced), which a lease's first call carries alone: `bash tools/device_job.sh place .xla` unpacks
it on the machine before the training calls; `fit` takes them back into the carried archive where the room allows.
"""
from __future__ import annotations

import os
import sys
import tarfile
from contextlib import ExitStack
from pathlib import Path

MAX_MB = 15.0       # what one file from $OUT may be (16 MiB), less a margin
#: what one call takes to the GPU machine (the checkout and what it carries). The device tool refused 63.6 MiB of files
#: in 230 folders (session 39), so it seems to count 4 KiB a folder too; fit also leaves a margin of 1 MiB.
CARRY_MB, FOLDER_BYTES, MARGIN_MB = 64.0, 4096, 1.0
#: JAX names a cache entry `jit_<function>-<key>-cache`: the trainer's jitted functions (mjx_morph/ppo/trainer.py)
TRAINING_PROGRAMS = ("jit__init_state", "jit__rollout", "jit__update", "jit__iteration")


def is_training_program(p: Path) -> bool:
    """Whether a cache entry is one of the trainer's programs (by the function name JAX puts before its key)."""
    return p.name.split("-", 1)[0] in TRAINING_PROGRAMS


def carried_list(cache: Path) -> Path:
    """Where unpack lists the files it wrote (relative paths), so that pack can tell them apart: beside the cache
    directory, not in it (JAX's own)."""
    return cache.parent / f"{cache.name}.carried"


def pack(cache: Path, archive: Path, max_mb: float = MAX_MB) -> tuple[int, int, int]:
    """The cache's files into `archive` while their sizes add up to at most `max_mb` MiB (a file that would cross it
    is left out, and smaller later ones still go; the entries are compressed already, gzip gains little), in this
    order: the training programs (`TRAINING_PROGRAMS`) before the others, and within each, the programs compiled here,
    oldest first; then those an earlier lease brought (`unpack`), the ones read since (a hit: the file system set their
    access time after the modification time that unpack gave them) before the others, newest first within each. So
    programs that no longer match the code give way to the new ones. Returns (files packed, files in the cache, bytes
    of the cache)."""
    marker = carried_list(cache)
    carried = set(marker.read_text().split("\n")) - {""} if marker.is_file() else set()
    files = [p for p in cache.rglob("*") if p.is_file()]

    def rank(p: Path):
        st, kind = p.stat(), 0 if is_training_program(p) else 1
        if str(p.relative_to(cache)) not in carried:
            return (kind, 0, st.st_mtime, str(p))
        return (kind, 1 if st.st_atime > st.st_mtime else 2, -st.st_mtime, str(p))
    files.sort(key=rank)
    total, limit, size, keep = sum(p.stat().st_size for p in files), int(max_mb * 2 ** 20), 0, []
    for p in files:
        if size + p.stat().st_size > limit:
            continue
        size += p.stat().st_size
        keep.append(p)
    archive.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(archive, "w:gz") as tar:
        for p in keep:
            tar.add(p, arcname=str(p.relative_to(cache)))
    return len(keep), len(files), total


def unpack(archive: Path, cache: Path) -> int:
    """Extract `archive` into `cache` (plain files only, no paths outside it, their times as packed) and list them in
    `carried_list(cache)`; returns the files in the archive. A file already there with the archive's size is left as
    it is: on a warm machine a call without --continue unpacks again, and rewriting would reset the access times by
    which `pack` knows what the earlier calls read (session 47 lost a program that way)."""
    cache.mkdir(parents=True, exist_ok=True)
    with tarfile.open(archive, "r:gz") as tar:
        members = [m for m in tar.getmembers() if m.isfile()]
        new = [m for m in members if not ((cache / m.name).is_file() and (cache / m.name).stat().st_size == m.size)]
        tar.extractall(cache, members=new, filter="data")
    marker = carried_list(cache)          # every archive unpacked on this machine (the overflow's and .gpu's) counts
    listed = marker.read_text().split("\n") if marker.is_file() else []
    names = list(dict.fromkeys([n for n in listed if n] + [m.name for m in members]))
    marker.write_text("".join(f"{n}\n" for n in names))
    return len(members)


def _write(out: Path, members: list[tuple[tarfile.TarFile, tarfile.TarInfo]]) -> None:
    """`members` (each with the archive it is read from) into `out`, their times kept, through a temporary file."""
    tmp = out.with_name(out.name + ".part")
    with tarfile.open(tmp, "w:gz") as w:
        for tar, m in members:
            w.addfile(m, tar.extractfile(m))
    tmp.replace(out)


def _members(stack: ExitStack, archive: Path, skip: set[str] = frozenset()) -> list:
    """The files of `archive` (opened in `stack`), each with the archive to read it from, but those named in `skip`;
    none where `archive` is missing."""
    if not archive.is_file():
        return []
    tar = stack.enter_context(tarfile.open(archive, "r:gz"))
    return [(tar, m) for m in tar.getmembers() if m.isfile() and m.name not in skip]


def _within(members: list, limit: int) -> tuple[list, list]:
    """`members` split into those kept while their sizes add up to at most `limit` bytes (one that would cross it is
    left out, and smaller later ones still go, as in `pack`) and the rest."""
    keep, rest, size = [], [], 0
    for tm in members:
        if size + tm[1].size <= limit:
            size += tm[1].size
            keep.append(tm)
        else:
            rest.append(tm)
    return keep, rest


def fit(archive: Path, max_mb: float, overflow: Path | None = None, overflow_mb: float = 0.0) -> tuple[int, int, int]:
    """Rewrite `archive` with the most useful programs on hand while their sizes add up to at most `max_mb` MiB,
    their times kept for `unpack`: so the carry stays within what a call takes as the checkout grows, and takes back
    what it has room for when what else travels shrinks (tools/device_job.sh fit). On hand: the archive's programs in
    pack's order (the most useful first), then, with `overflow`, the overflow's own that the archive lacks, in its
    order (`merge` puts the programs of the archive a lease's new cache replaced first). With `overflow`, those that
    gave way go there, within `overflow_mb` MiB (none left: no overflow). Returns (programs kept, programs on hand,
    programs in the overflow)."""
    with ExitStack() as stack:
        members = _members(stack, archive)
        before = [m.name for _, m in members]
        if overflow is not None:
            members += _members(stack, overflow, set(before))
        keep, rest = _within(members, int(max_mb * 2 ** 20))
        spilled = []
        if overflow is not None:
            spilled, _ = _within(rest, int(overflow_mb * 2 ** 20))
            if spilled:
                overflow.parent.mkdir(parents=True, exist_ok=True)
                _write(overflow, spilled)
            elif overflow.is_file():
                overflow.unlink()
        if [m.name for _, m in keep] != before:
            _write(archive, keep)
    return len(keep), len(members), len(spilled)


def merge(first: Path, into: Path) -> int:
    """`into` rewritten as `first`'s members followed by its own that `first` lacks (by name), times kept: `home`
    keeps the programs of the archive a lease's new cache replaces, ahead of the older overflow. Returns the members
    of `into` after."""
    if not first.is_file():
        return 0
    with ExitStack() as stack:
        members = _members(stack, first)
        members += _members(stack, into, {m.name for _, m in members})
        into.parent.mkdir(parents=True, exist_ok=True)
        _write(into, members)
    return len(members)


def room_mb(files: list[str]) -> float:
    """MiB left for the carried cache when `files` (the rest of what travels) go too: their sizes and 4 KiB for each
    folder they sit in (ancestors too), less the margin."""
    files = [f for f in files if os.path.isfile(f)]
    folders = set()
    for f in files:
        d = os.path.dirname(f)
        while d and d not in folders:
            folders.add(d)
            d = os.path.dirname(d)
    used = sum(os.path.getsize(f) for f in files) + FOLDER_BYTES * (len(folders) + 1)      # + the root
    return CARRY_MB - MARGIN_MB - used / 2 ** 20


def main(argv: list[str]) -> int:
    if len(argv) >= 3 and argv[0] == "pack":
        cache, archive = Path(argv[1]), Path(argv[2])
        if not cache.is_dir():
            print(f"[xla_cache] {cache}: no compilation cache here; nothing packed")
            return 0
        packed, count, total = pack(cache, archive, float(argv[3]) if len(argv) > 3 else MAX_MB)
        print(f"[xla_cache] {packed} of {count} compiled programs ({total / 2 ** 20:.1f} MiB in the cache) -> "
              f"{archive} ({archive.stat().st_size / 2 ** 20:.1f} MiB)")
        return 0
    if len(argv) == 3 and argv[0] == "unpack":
        n = unpack(Path(argv[1]), Path(argv[2]))
        print(f"[xla_cache] {n} compiled programs from {argv[1]} in {argv[2]} (used only where the GPU model, JAX "
              "and the program are the same)")
        return 0
    if len(argv) in (2, 3) and argv[0] == "fit":
        files = [f for f in sys.stdin.read().split("\0") if f]
        room = room_mb(files)
        print(f"[xla_cache] what else travels: {CARRY_MB - MARGIN_MB - room:.1f} MiB of {CARRY_MB:.0f}")
        if room <= 0:
            print(f"[xla_cache] no room for {argv[1]}: what else travels takes the {CARRY_MB:.0f} MiB already; "
                  "carry less", file=sys.stderr)
            return 1
        overflow = Path(argv[2]) if len(argv) == 3 else None
        # the overflow's call carries the checkout alone beside it (not the wheels, not .gpu)
        overflow_room = room_mb([f for f in files if not f.startswith((".whl/", ".gpu/"))]) if overflow else 0.0
        kept, count, spilled = fit(Path(argv[1]), room, overflow, overflow_room)
        print(f"[xla_cache] {argv[1]}: {kept} of {count} compiled programs kept within {room:.1f} MiB "
              f"({Path(argv[1]).stat().st_size / 2 ** 20:.1f} MiB packed)")
        if overflow is not None:
            size = f" ({overflow.stat().st_size / 2 ** 20:.1f} MiB packed)" if overflow.is_file() else ""
            print(f"[xla_cache] {overflow}: {spilled} compiled programs within {overflow_room:.1f} MiB{size}"
                  + (f"; carry it in the lease's first call: bash tools/device_job.sh place {overflow.parent} "
                     f"(carry: [\"{overflow.parent}\"])" if spilled else ""))
        return 0
    print("usage: python3 tools/xla_cache.py pack <cache dir> <archive.tar.gz> [max MiB] | "
          "unpack <archive.tar.gz> <cache dir> | fit <archive.tar.gz> [<overflow.tar.gz>] (the other files on stdin)",
          file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
