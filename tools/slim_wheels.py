"""Drop from the wheels the GPU machine gets (.whl/, carried by every training call) what neither training nor
evaluation reads, so that the carried compilation cache has the room (tools/device_job.sh prepare).

    python3 tools/slim_wheels.py .whl

A call takes at most 64 MiB: the checkout, the wheels and `.gpu/` with the compilation cache, which gets what the
rest leaves (tools/xla_cache.py, `room_mb`). Two wheels go whole: mujoco-studio is MuJoCo's viewer (12.8 MB) and
pyopengl (3.2 MB) serves rendering alone; `mujoco` and `mujoco.mjx` import without them, and a smoke run with OpenGL
unimportable trains and evaluates (rendering on the GPU host would need pyopengl). mujoco-mjx's wheel (6.9 MiB) is
mostly MJX's own test robots (`mujoco/mjx/test_data/`, 6.2 MiB packed: meshes and textures of barkour, shadow_hand,
humanoid, ...), which only MJX's tests and its `testspeed` script read. In session 85 the cache had 10.2 MiB of room:
both models' training programs (10.3 MiB, beside small autotuning entries) did not fit, and R-MoMo's initial state
went to the overflow; without the test robots it has 16.4 MiB. The wheel is rewritten without those files and without
their RECORD rows (pip installs it as the original, by its unchanged name); a wheel already slim is left as it is.
Plain Python.
"""
from __future__ import annotations

import sys
import zipfile
from pathlib import Path

#: wheels (name prefixes) that nothing of ours imports on the GPU host
UNUSED = ("mujoco_studio-", "pyopengl-")
#: (wheel name prefix, folders inside the wheel that nothing of ours reads)
UNREAD = (("mujoco_mjx-", ("mujoco/mjx/test_data/",)),)


def slim(wheel: Path, folders: tuple[str, ...]) -> tuple[int, int]:
    """Rewrite `wheel` without the members under `folders` and their rows in its RECORD (through a temporary file).
    Returns (bytes before, bytes after); the same where nothing is under them."""
    before = wheel.stat().st_size
    with zipfile.ZipFile(wheel) as z:
        infos = z.infolist()
        drop = {i.filename for i in infos if i.filename.startswith(folders)}
        if not drop:
            return before, before
        records = [i for i in infos if i.filename.endswith(".dist-info/RECORD")]
        if len(records) != 1:
            raise SystemExit(f"{wheel}: expected one .dist-info/RECORD in the wheel, found {len(records)}")
        tmp = wheel.with_name(wheel.name + ".part")
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as out:
            for i in infos:
                if i.filename in drop:
                    continue
                data = z.read(i)
                if i is records[0]:
                    rows = data.decode().splitlines(keepends=True)
                    data = "".join(r for r in rows if r.split(",", 1)[0] not in drop).encode()
                out.writestr(i, data)
    tmp.replace(wheel)
    return before, wheel.stat().st_size


def main(argv: list[str]) -> int:
    if len(argv) != 1 or not Path(argv[0]).is_dir():
        print("usage: python3 tools/slim_wheels.py <folder of wheels>", file=sys.stderr)
        return 2
    for prefix in UNUSED:
        for wheel in sorted(Path(argv[0]).glob(f"{prefix}*.whl")):
            wheel.unlink()
            print(f"[slim_wheels] {wheel}: removed (not imported on the GPU host)")
    for prefix, folders in UNREAD:
        for wheel in sorted(Path(argv[0]).glob(f"{prefix}*.whl")):
            before, after = slim(wheel, folders)
            if after != before:
                print(f"[slim_wheels] {wheel}: {before / 2 ** 20:.1f} -> {after / 2 ** 20:.1f} MiB "
                      f"(without {', '.join(folders)})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
