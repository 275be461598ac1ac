"""tools/device_job.sh, the wrapper of a command on a lent GPU machine: the checks that run before anything is
installed (the machine's wheels and GPU are not here)."""
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "tools" / "device_job.sh"


def job(*args, cwd, out=None, **extra_env):
    env = {"PATH": "/usr/bin:/bin", **({"OUT": str(out)} if out else {}), **extra_env}
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=cwd, env=env, capture_output=True, text=True)


def load_tool(name: str):
    """tools/<name>.py as a module (tools/ is not a package)."""
    import importlib
    import sys
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.pop(0)


def stand_in_machine(gpu: Path) -> Path:
    """A checkout as a GPU call sees it, with a stand-in wheel that pip installs, so that device_job.sh runs whole."""
    import zipfile
    (gpu / ".whl").mkdir(parents=True)
    with zipfile.ZipFile(gpu / ".whl" / "stand_in-0.0.0-py3-none-any.whl", "w") as whl:
        whl.writestr("stand_in-0.0.0.dist-info/METADATA", "Metadata-Version: 2.1\nName: stand-in\nVersion: 0.0.0\n")
        whl.writestr("stand_in-0.0.0.dist-info/WHEEL",
                     "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n")
        whl.writestr("stand_in-0.0.0.dist-info/RECORD", "stand_in-0.0.0.dist-info/METADATA,,\n"
                     "stand_in-0.0.0.dist-info/WHEEL,,\nstand_in-0.0.0.dist-info/RECORD,,\n")
    (gpu / "tools").symlink_to(SCRIPT.parent)
    return gpu


def stand_in_env(tmp_path: Path, **extra) -> dict:
    """The environment of a device_job.sh call on a stand-in machine: this Python on PATH, the wheels installed
    under tmp_path."""
    import sys
    return {"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "DEVICE_JOB_SITE": str(tmp_path / "site"), **extra}


def test_continue_refuses_a_fresh_machine_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    r = job("--continue", "fp32", "touch", str(marker), cwd=tmp_path, out=tmp_path)
    assert r.returncode == 3 and "runs/ is not here: this is a fresh machine" in r.stderr
    assert not marker.exists()


def test_usage_and_missing_out(tmp_path):
    r = job("only-a-name", cwd=tmp_path, out=tmp_path)
    assert r.returncode == 2 and "usage: bash tools/device_job.sh" in r.stderr
    r = job("name", "true", cwd=tmp_path)
    assert r.returncode == 2 and "$OUT is not set" in r.stderr
    r = job("send", cwd=tmp_path)
    assert r.returncode == 2 and "$OUT is not set" in r.stderr


def test_the_time_limit_leaves_room_to_stop_and_pack(tmp_path):
    # a limit past 570 s is lowered, with a warning, before anything is installed (here nothing installs: no .whl)
    marker = tmp_path / "ran"
    r = job("name", "touch", str(marker), cwd=tmp_path, out=tmp_path, DEVICE_JOB_LIMIT_S="588")
    assert "DEVICE_JOB_LIMIT_S=588 leaves too little" in r.stderr and "570 used" in r.stderr
    assert r.returncode == 1 and "the wheels did not install" in r.stderr and not marker.exists()
    r = job("name", "true", cwd=tmp_path, out=tmp_path, DEVICE_JOB_LIMIT_S="9m")
    assert r.returncode == 2 and "DEVICE_JOB_LIMIT_S=9m: expected whole seconds" in r.stderr
    r = job("name", "true", cwd=tmp_path, out=tmp_path, DEVICE_JOB_LIMIT_S="500")
    assert "too little" not in r.stderr and "the wheels did not install" in r.stderr


def test_the_carried_cache_is_unpacked_on_a_fresh_machine_even_by_a_continuing_call(tmp_path):
    """The first training call after `place` calls is a --continue call on a fresh machine (the placed run is put
    back, so it runs): it starts from the carried compilation cache too (session 66's plan found that it did not, and
    would have compiled R-MoMo's train step anew, ~140 s); a --continue call on a warm machine leaves the cache be."""
    xla_cache = load_tool("xla_cache")
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "jit_train_step-abc").write_bytes(b"program")
    gpu = stand_in_machine(tmp_path / "gpu")
    (gpu / ".gpu").mkdir()
    xla_cache.pack(earlier, gpu / ".gpu" / "xla-cache.tar.gz")
    (gpu / "runs" / "studies" / "paper" / "ft-rmomo-main-s3").mkdir(parents=True)     # as `place` would put back
    cache = tmp_path / "xla"
    env = stand_in_env(tmp_path, MJX_MORPH_XLA_CACHE=str(cache))
    r = job("--continue", "rm3d", "true", cwd=gpu, out=tmp_path, **env)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (cache / "jit_train_step-abc").read_bytes() == b"program"
    (cache / "jit_train_step-abc").unlink()                 # a warm machine's cache, as its calls left it
    r = job("--continue", "rm3e", "true", cwd=gpu, out=tmp_path, **env)
    assert r.returncode == 0 and not (cache / "jit_train_step-abc").exists(), r.stdout + r.stderr


def test_the_lease_clock_ends_a_command_at_its_time_after_the_machines_first_call(tmp_path):
    """DEVICE_JOB_UNTIL_S counts from the machine's first call (noted once, in .lease-start), so that a batch's last
    call can spend what the calls before it left; a time already past runs nothing, and the artefacts still pack."""
    import time
    gpu = stand_in_machine(tmp_path / "gpu")
    env = stand_in_env(tmp_path)
    r = job("place", "nowhere", cwd=gpu, out=tmp_path, **env)             # a first call, even a failing one
    first = int((gpu / ".lease-start").read_text())
    assert abs(first - time.time()) < 5
    (gpu / ".lease-start").write_text(f"{first - 100}\n")                # as if the first call was 100 s ago
    r = job("name", "true", cwd=gpu, out=tmp_path, **env)
    assert r.returncode == 0 and int((gpu / ".lease-start").read_text()) == first - 100, r.stdout + r.stderr
    assert "the machine's first call began 10" in (tmp_path / "name.log").read_text()
    start = time.monotonic()
    r = job("slow", "sleep", "60", cwd=gpu, out=tmp_path, DEVICE_JOB_UNTIL_S="104", **env)
    assert r.returncode == 124 and time.monotonic() - start < 30, r.stdout + r.stderr
    assert "interrupted 104 s after the machine's first call (DEVICE_JOB_UNTIL_S)" in r.stdout
    marker = tmp_path / "ran"
    r = job("late", "touch", str(marker), cwd=gpu, out=tmp_path, DEVICE_JOB_UNTIL_S="60", **env)
    assert r.returncode == 124 and not marker.exists()
    assert "no time left before 60 s after the machine's first call" in (tmp_path / "late.log").read_text()
    r = job("ok", "touch", str(marker), cwd=gpu, out=tmp_path, DEVICE_JOB_UNTIL_S="900", **env)
    assert r.returncode == 0 and marker.exists() and "interrupted" not in r.stdout
    r = job("bad", "true", cwd=gpu, out=tmp_path, DEVICE_JOB_UNTIL_S="1e3", **env)
    assert r.returncode == 2 and "DEVICE_JOB_UNTIL_S=1e3: expected whole seconds" in r.stderr


def test_xla_cache_travels_oldest_programs_first_within_its_size(tmp_path):
    """tools/xla_cache.py: pack takes the cache's files oldest first while they fit max MiB (a lease compiles its
    training programs first; one too large is left out, smaller later ones still go), unpack puts them back byte for
    byte, and the CLI says what it did."""
    import os
    import sys
    xla_cache = load_tool("xla_cache")
    cache = tmp_path / "xla"
    (cache / "sub").mkdir(parents=True)
    sizes = {"train-step": 600_000, "init": 300_000, "sub/variants-sweep": 500_000, "test-sweep": 100_000}
    for age, (name, size) in enumerate(sizes.items()):
        p = cache / name
        p.write_bytes(os.urandom(size))
        os.utime(p, (1_000_000 + age, 1_000_000 + age))        # in this order, oldest first
    packed, count, total = xla_cache.pack(cache, tmp_path / "out" / "xla.tar.gz", max_mb=1_000_000 / 2 ** 20)
    assert (packed, count, total) == (3, 4, sum(sizes.values()))      # 600 k + 300 k + 100 k: 500 k did not fit
    back = tmp_path / "back"
    assert xla_cache.unpack(tmp_path / "out" / "xla.tar.gz", back) == 3
    assert {p.name for p in back.rglob("*") if p.is_file()} == {"train-step", "init", "test-sweep"}
    assert (back / "train-step").read_bytes() == (cache / "train-step").read_bytes()
    r = subprocess.run([sys.executable, str(SCRIPT.parent / "xla_cache.py"), "pack", str(cache),
                        str(tmp_path / "all.tar.gz")], capture_output=True, text=True)
    assert r.returncode == 0 and "4 of 4 compiled programs (1.4 MiB in the cache)" in r.stdout
    r = subprocess.run([sys.executable, str(SCRIPT.parent / "xla_cache.py"), "pack", str(tmp_path / "none"),
                        str(tmp_path / "x.tar.gz")], capture_output=True, text=True)
    assert r.returncode == 0 and "no compilation cache here" in r.stdout and not (tmp_path / "x.tar.gz").exists()
    r = subprocess.run([sys.executable, str(SCRIPT.parent / "xla_cache.py"), "copy"], capture_output=True, text=True)
    assert r.returncode == 2 and "usage:" in r.stderr


def test_xla_cache_packs_this_leases_programs_before_carried_ones(tmp_path):
    """After an unpack, pack takes the programs compiled since first (oldest first), then the carried ones that were
    read (access time after modification time) before the unread, newest first: stale programs give way."""
    import os
    import tarfile
    xla_cache = load_tool("xla_cache")
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    for name in ("hit", "stale-old", "stale-new"):
        (earlier / name).write_bytes(os.urandom(100_000))
    xla_cache.pack(earlier, tmp_path / "carried.tar.gz")
    cache = tmp_path / "xla"
    assert xla_cache.unpack(tmp_path / "carried.tar.gz", cache) == 3
    assert set(xla_cache.carried_list(cache).read_text().split()) == {"hit", "stale-old", "stale-new"}
    times = {"hit": (3000, 1000), "stale-old": (1500, 1500), "stale-new": (2000, 2000),     # (access, modification)
             "new-update": (5000, 5000), "new-init": (4000, 4000)}
    for name in ("new-update", "new-init"):
        (cache / name).write_bytes(os.urandom(100_000))
    for name, t in times.items():
        os.utime(cache / name, t)
    packed, count, _ = xla_cache.pack(cache, tmp_path / "out.tar.gz", max_mb=450_000 / 2 ** 20)
    assert (packed, count) == (4, 5)
    with tarfile.open(tmp_path / "out.tar.gz") as tar:
        assert tar.getnames() == ["new-init", "new-update", "hit", "stale-new"]


def test_xla_cache_unpacked_again_keeps_what_the_earlier_calls_read(tmp_path):
    """A second unpack on a warm machine (a call without --continue) leaves a program already there as it is, with
    the access time that marks it read, so pack still ranks it among the read ones; a file whose size differs from
    the archive's is written again."""
    import os
    import tarfile
    xla_cache = load_tool("xla_cache")
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    for name in ("read-old", "unread-new"):
        (earlier / name).write_bytes(os.urandom(100_000))
    os.utime(earlier / "read-old", (1000, 1000))
    os.utime(earlier / "unread-new", (2000, 2000))
    xla_cache.pack(earlier, tmp_path / "carried.tar.gz")
    cache = tmp_path / "xla"
    assert xla_cache.unpack(tmp_path / "carried.tar.gz", cache) == 2
    os.utime(cache / "read-old", (5000, 1000))                     # the first call read it
    (cache / "unread-new").write_bytes(b"truncated")               # a damaged copy
    assert xla_cache.unpack(tmp_path / "carried.tar.gz", cache) == 2
    assert (cache / "read-old").stat().st_atime == 5000
    xla_cache.pack(cache, tmp_path / "out.tar.gz", max_mb=150_000 / 2 ** 20)     # room for one: the read one
    with tarfile.open(tmp_path / "out.tar.gz") as tar:
        assert tar.getnames() == ["read-old"]
    assert (cache / "unread-new").read_bytes() == (earlier / "unread-new").read_bytes()   # (reading it marks it)


def test_xla_cache_packs_training_programs_before_the_others(tmp_path):
    """The trainer's programs (jit__rollout, jit__update, ...: what a lease's first iteration waits for) go before the
    others, also a carried one nobody read before this lease's sweeps; within each kind the order stays."""
    import os
    import tarfile
    xla_cache = load_tool("xla_cache")
    key = "0" * 64
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    for name in (f"jit__update-{key}-cache", f"jit__sweep-{key}-cache"):
        (earlier / name).write_bytes(os.urandom(100_000))
    xla_cache.pack(earlier, tmp_path / "carried.tar.gz")
    cache = tmp_path / "xla"
    xla_cache.unpack(tmp_path / "carried.tar.gz", cache)
    new = {f"jit__rollout-{'1' * 64}-cache": 5000, f"jit__sweep-{'2' * 64}-cache": 4000,
           f"jit__sweep-{'3' * 64}-cache": 6000}
    for name, t in new.items():
        (cache / name).write_bytes(os.urandom(100_000))
        os.utime(cache / name, (t, t))
    for name in (f"jit__update-{key}-cache", f"jit__sweep-{key}-cache"):     # carried, not read here
        os.utime(cache / name, (1000, 1000))
    packed, count, _ = xla_cache.pack(cache, tmp_path / "out.tar.gz", max_mb=350_000 / 2 ** 20)
    assert (packed, count) == (3, 5)
    with tarfile.open(tmp_path / "out.tar.gz") as tar:
        assert [n.split("-")[0] + n.split("-")[1][:1] for n in tar.getnames()] == \
            ["jit__rollout1", "jit__update0", "jit__sweep2"]


def test_the_overflow_is_placed_first_and_the_first_training_call_still_unpacks_gpus_cache(tmp_path):
    """`place .xla` (a lease's first call) unpacks the cache's overflow on the fresh machine; the first training call
    after it, a --continue call, still unpacks .gpu's archive although the cache folder exists already, and both
    archives' programs count as carried (pack ranks this lease's own before them)."""
    xla_cache = load_tool("xla_cache")
    gpu = stand_in_machine(tmp_path / "gpu")
    for folder, name in ((".xla", "jit__rollout-over-cache"), (".gpu", "jit__update-main-cache")):
        src = tmp_path / f"src{folder}"
        src.mkdir()
        (src / name).write_bytes(name.encode())
        (gpu / folder).mkdir()
        xla_cache.pack(src, gpu / folder / "xla-cache.tar.gz")
    cache = tmp_path / "xla"
    env = stand_in_env(tmp_path, MJX_MORPH_XLA_CACHE=str(cache))
    r = job("place", ".xla", cwd=gpu, out=tmp_path, **env)
    assert r.returncode == 0 and sorted(p.name for p in cache.iterdir()) == ["jit__rollout-over-cache"], r.stderr
    (gpu / "runs" / "studies" / "ab" / "incline-rmomo-s1").mkdir(parents=True)     # as `place .mv1` would put back
    r = job("--continue", "ri1d", "true", cwd=gpu, out=tmp_path, **env)
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(p.name for p in cache.iterdir()) == ["jit__rollout-over-cache", "jit__update-main-cache"]
    assert sorted(xla_cache.carried_list(cache).read_text().split()) == ["jit__rollout-over-cache",
                                                                         "jit__update-main-cache"]


def test_fit_spills_what_gives_way_into_the_overflow_and_home_keeps_the_replaced_archive(tmp_path):
    """`fit` with an overflow: the programs that do not fit the carry beside the wheels go to .xla/, ahead of the
    overflow's own, within the room of a call that carries the checkout and .xla alone; `merge` (home, before a new
    cache replaces .gpu's) puts the replaced archive's programs at the overflow's front, each program once; and where
    the carry has room again, the overflow's programs come back into .gpu's archive, in the overflow's order."""
    import os
    import tarfile
    xla_cache = load_tool("xla_cache")

    def archive(path: Path, names: list[str], mib: float = 3.0) -> Path:
        src = tmp_path / f"src{path.parent.name}"          # outside the checkout
        src.mkdir(parents=True)
        for age, name in enumerate(names):
            (src / name).write_bytes(os.urandom(int(mib * 2 ** 20)))      # incompressible
            os.utime(src / name, (1_000_000 + age, 1_000_000 + age))
        path.parent.mkdir(parents=True, exist_ok=True)
        xla_cache.pack(src, path, max_mb=100)
        return path

    def names(path: Path) -> list[str]:
        with tarfile.open(path) as tar:
            return tar.getnames()

    repo = tmp_path / "repo"
    main = archive(repo / ".gpu" / "xla-cache.tar.gz", ["jit__update-a-cache", "jit__rollout-b-cache",
                                                         "jit__init_state-c-cache"])
    over = archive(repo / ".xla" / "xla-cache.tar.gz", ["jit__update-old-cache", "jit__rollout-b-cache"])
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    (repo / ".gitignore").write_text(".gpu/\n.xla/\n.whl/\n")
    (repo / "results.bin").write_bytes(os.urandom(50 * 2 ** 20))      # the checkout: 64 - 1 - 50 MiB of room
    (repo / ".whl").mkdir()
    (repo / ".whl" / "w.whl").write_bytes(os.urandom(5 * 2 ** 20))    # beside the wheels: 64 - 1 - 55 MiB
    r = job("fit", cwd=repo)
    assert r.returncode == 0 and "2 of 4 compiled programs kept" in r.stdout, r.stdout + r.stderr
    assert "xla-cache.tar.gz: 2 compiled programs within" in r.stdout and "place .xla" in r.stdout
    assert names(main) == ["jit__update-a-cache", "jit__rollout-b-cache"]
    assert names(over) == ["jit__init_state-c-cache", "jit__update-old-cache"]      # b is in the main archive
    with tarfile.open(over) as tar:
        assert tar.getmember("jit__update-old-cache").mtime == 1_000_000      # times kept for unpack's ranks
    assert xla_cache.merge(main, over) == 4
    assert names(over) == ["jit__update-a-cache", "jit__rollout-b-cache", "jit__init_state-c-cache",
                           "jit__update-old-cache"]
    assert xla_cache.merge(tmp_path / "none.tar.gz", over) == 0 and len(names(over)) == 4
    call = tmp_path / "files1"                       # a lease's call with a finished run and a new cache: home
    run = tmp_path / "machine" / "ab" / "ft-rmomo-s0"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text("arch: rmomo\ntotal_steps: 100000000\nstop_at: 2\n")
    (run / "metrics.csv").write_text("iteration\n1\n2\n")
    call.mkdir()
    (call / "zs.log").write_text("call 1\n")
    with tarfile.open(call / "zs-runs.tar.gz", "w:gz") as tf:
        tf.add(tmp_path / "machine" / "ab", arcname="ab")
    archive(call / "xla-cache.tar.gz", ["jit__update-new-cache"], mib=0.1)
    done = load_tool("bring_home").bring_home(tmp_path / "results" / "ab_s74", [call], repo / ".gpu")
    assert any("to the front of" in line for line in done)
    assert names(main) == ["jit__update-new-cache"]
    assert names(over) == ["jit__update-a-cache", "jit__rollout-b-cache", "jit__init_state-c-cache",
                           "jit__update-old-cache"]
    kept, count, spilled = xla_cache.fit(main, 6.2, over, 100.0)     # room for two more: the overflow's first two
    assert (kept, count, spilled) == (3, 5, 2)
    assert names(main) == ["jit__update-new-cache", "jit__update-a-cache", "jit__rollout-b-cache"]
    assert names(over) == ["jit__init_state-c-cache", "jit__update-old-cache"]
    with tarfile.open(main) as tar:
        assert tar.getmember("jit__update-a-cache").mtime == 1_000_000
    assert xla_cache.fit(main, 100.0, over, 100.0) == (5, 5, 0) and not over.exists()     # room for all: it goes
    assert names(main)[3:] == ["jit__init_state-c-cache", "jit__update-old-cache"]
    kept, count, spilled = xla_cache.fit(main, 3.1, over, 0.0)     # no room for an overflow: what gives way is lost
    assert (kept, count, spilled) == (2, 5, 0) and not over.exists()
    assert names(main) == ["jit__update-new-cache", "jit__update-a-cache"]


def test_slim_wheels_drops_mjxs_test_robots_and_their_record_rows_and_pip_installs_the_rest(tmp_path):
    """`prepare` removes the viewer's wheel and rewrites mujoco-mjx's without MJX's own test robots (6.2 MiB of the
    64 a call carries, room for the compilation cache): the members under mujoco/mjx/test_data/ and their RECORD
    rows go, the rest stays byte for byte, pip installs it, and a second run (or a wheel without them) leaves the
    file untouched."""
    import sys
    import zipfile
    slim_wheels = load_tool("slim_wheels")
    whl = tmp_path / ".whl"
    whl.mkdir()
    wheel = whl / "mujoco_mjx-9.9.9-py3-none-any.whl"
    keep = {"mujoco/mjx/__init__.py": "X = 1\n", "mujoco/mjx/_src/io.py": "Y = 2\n",
            "mujoco_mjx-9.9.9.dist-info/METADATA": "Metadata-Version: 2.1\nName: mujoco-mjx\nVersion: 9.9.9\n",
            "mujoco_mjx-9.9.9.dist-info/WHEEL":
                "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"}
    drop = {"mujoco/mjx/test_data/humanoid/humanoid.xml": "<mujoco/>\n", "mujoco/mjx/test_data/a.stl": "x" * 5000}
    record = "".join(f"{n},,\n" for n in [*keep, *drop]) + "mujoco_mjx-9.9.9.dist-info/RECORD,,\n"
    with zipfile.ZipFile(wheel, "w", zipfile.ZIP_DEFLATED) as z:
        for name, text in {**keep, **drop, "mujoco_mjx-9.9.9.dist-info/RECORD": record}.items():
            z.writestr(name, text)
    other = whl / "trimesh-1.0-py3-none-any.whl"
    other.write_bytes(wheel.read_bytes())                    # another package's wheel: not touched
    viewer = whl / "mujoco_studio-9.9.9-py3-none-any.whl"
    viewer.write_bytes(b"viewer")                            # the viewer's wheel: not carried at all
    assert slim_wheels.main([str(whl)]) == 0
    assert not viewer.exists()
    with zipfile.ZipFile(wheel) as z:
        assert sorted(z.namelist()) == sorted([*keep, "mujoco_mjx-9.9.9.dist-info/RECORD"])
        assert all(z.read(n).decode() == text for n, text in keep.items())
        rows = z.read("mujoco_mjx-9.9.9.dist-info/RECORD").decode().splitlines()
    assert [r.split(",")[0] for r in rows] == [*keep, "mujoco_mjx-9.9.9.dist-info/RECORD"]
    assert other.read_bytes() != wheel.read_bytes() and len(zipfile.ZipFile(other).namelist()) == 7
    stat = wheel.stat()
    assert slim_wheels.main([str(whl)]) == 0 and wheel.stat().st_mtime_ns == stat.st_mtime_ns      # already slim
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                        "--target", str(site), str(wheel)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (site / "mujoco" / "mjx" / "_src" / "io.py").read_text() == "Y = 2\n"
    assert not (site / "mujoco" / "mjx" / "test_data").exists()
    assert slim_wheels.main([str(tmp_path / "none")]) == 2


def test_fit_shrinks_the_carried_cache_to_the_room_the_checkout_leaves(tmp_path):
    """`device_job.sh fit` (here, after copying a lease's cache to .gpu/): what travels is at most 64 MiB, the
    checkout grows with the results, and the cache gives way: its first programs (pack's order, the most useful) stay,
    with their times (unpack ranks the carried ones by them), the rest go; a cache that fits is left as it was."""
    import os
    xla_cache = load_tool("xla_cache")
    cache = tmp_path / "xla"
    cache.mkdir()
    for age, name in enumerate(["jit__update-a-cache", "jit__rollout-b-cache", "jit_sweep-c-cache"]):
        (cache / name).write_bytes(os.urandom(3 * 2 ** 20))         # 3 MiB each, incompressible
        os.utime(cache / name, (1_000_000 + age, 1_000_000 + age))
    repo = tmp_path / "repo"
    (repo / ".gpu").mkdir(parents=True)
    archive = repo / ".gpu" / "xla-cache.tar.gz"
    xla_cache.pack(cache, archive)
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    (repo / ".gitignore").write_text(".gpu/\n.xla/\n")
    r = job("fit", cwd=repo)                       # 9 MiB of cache, nothing else: it fits
    assert r.returncode == 0 and "3 of 3 compiled programs kept" in r.stdout, r.stdout + r.stderr
    (repo / "results.bin").write_bytes(os.urandom(55 * 2 ** 20))   # the checkout grows: 64 - 55 - 1 < 9 MiB
    r = job("fit", cwd=repo)
    assert r.returncode == 0 and "2 of 3 compiled programs kept" in r.stdout, r.stdout + r.stderr
    back = tmp_path / "back"
    assert xla_cache.unpack(archive, back) == 2
    assert sorted(p.name for p in back.iterdir()) == ["jit__rollout-b-cache", "jit__update-a-cache"]
    assert (back / "jit__update-a-cache").stat().st_mtime == 1_000_000
    assert (back / "jit__rollout-b-cache").read_bytes() == (cache / "jit__rollout-b-cache").read_bytes()
    (repo / "results.bin").write_bytes(os.urandom(64 * 2 ** 20))   # no room at all: said, and the cache kept
    r = job("fit", cwd=repo)
    assert r.returncode == 1 and "no room for .gpu/xla-cache.tar.gz" in r.stderr and archive.stat().st_size > 2 ** 20
    assert "what else travels: 64.0 MiB of 64" in r.stdout
    r = job("fit", cwd=tmp_path / "back")           # no .gpu/xla-cache.tar.gz: nothing to do
    assert r.returncode == 0 and "nothing to fit" in r.stdout


def test_a_run_moved_in_parts_is_placed_call_by_call_and_put_back_before_the_command(tmp_path):
    """tools/move_runs.py with device_job.sh: a run's newest checkpoint packed in parts as DEVICE_JOB_MOVE_OUT does
    (experiments.collect checkpoint=true, named by `name`), staged here two parts a folder, each folder placed on the
    machine by one call (`place`), then the next call puts the run back under runs/studies/<study>/ before anything
    else, byte for byte, and removes the parts; parts of a run already there at their checkpoint or later (a warm
    machine keeps a run it moved out) are dropped; with a part missing or corrupt, or the run there at an older
    checkpoint, it stops with exit status 4 before running anything and writes nothing of the run."""
    import os
    import sys
    from experiments import collect
    move_runs = load_tool("move_runs")
    run = tmp_path / "gpu" / "runs" / "studies" / "paper" / "ft-metamorph-main-s9"
    (run / "checkpoints" / "40").mkdir(parents=True)
    (run / "checkpoints" / "65" / "state").mkdir(parents=True)
    (run / "config.yaml").write_text("arch: metamorph\nseed: 9\n")
    (run / "checkpoints" / "40" / "old").write_bytes(os.urandom(50_000))
    blob = os.urandom(150_000)
    (run / "checkpoints" / "65" / "state" / "data").write_bytes(blob)
    name = move_runs.archive_name("runs/studies/paper/ft-metamorph-main-s9")
    assert name == "move.paper.ft-metamorph-main-s9.tar.gz"
    out = tmp_path / "out"
    out.mkdir()
    assert collect.main([f"runs=[{run}]", f"out={out / name}", "checkpoint=true", "part_mb=0.05"]) == 0
    parts = sorted(out.glob(name + ".*"))
    assert len(parts) == 3                                           # ~150 kB of 52 kB parts
    repo = tmp_path / "repo"
    repo.mkdir()
    r = subprocess.run([sys.executable, str(SCRIPT.parent / "move_runs.py"), "stage", str(out), str(repo / ".mv")],
                       capture_output=True, text=True)
    assert r.returncode == 0 and sorted(p.name for p in (repo / ".mv1").iterdir()) == [p.name for p in parts[:2]]
    assert "carry it in one call" in r.stdout and sorted((repo / ".mv2").iterdir())[0].name == parts[2].name
    for folder in (".mv1", ".mv2"):
        r = job("place", folder, cwd=repo, out=out)
        assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(p.name for p in (repo / "moving").iterdir()) == [p.name for p in parts]
    back = repo / "runs" / "studies" / "paper" / "ft-metamorph-main-s9"
    r = job("zs", "true", cwd=repo, out=out)            # no wheels here: the call stops at pip, after the move
    assert "moved in: runs/studies/paper/ft-metamorph-main-s9" in r.stdout, r.stdout + r.stderr
    assert (back / "checkpoints" / "65" / "state" / "data").read_bytes() == blob
    assert (back / "config.yaml").is_file() and not (back / "checkpoints" / "40").exists()
    assert list((repo / "moving").iterdir()) == []
    # the same parts again, now that the run is back (a warm machine keeps a run it moved out): dropped, the run kept
    for p in parts:
        (repo / "moving" / p.name).write_bytes(p.read_bytes())
    r = job("zs", "true", cwd=repo, out=out)
    assert "is here already at checkpoint 65" in r.stdout and "parts were dropped" in r.stdout, r.stdout + r.stderr
    assert list((repo / "moving").iterdir()) == [] and "exists already" not in r.stderr
    assert (back / "checkpoints" / "65" / "state" / "data").read_bytes() == blob
    # ... but where the run here is older than the parts: refused, nothing replaced
    (back / "checkpoints" / "65").rename(back / "checkpoints" / "30")
    for p in parts:
        (repo / "moving" / p.name).write_bytes(p.read_bytes())
    marker = repo / "ran"
    r = job("zs", "touch", str(marker), cwd=repo, out=out)
    assert r.returncode == 4 and "exists already" in r.stderr and not marker.exists()
    assert (back / "checkpoints" / "30").is_dir() and not (back / "checkpoints" / "65").exists()
    import shutil
    shutil.rmtree(repo / "runs")
    (repo / "moving" / parts[1].name).unlink()                    # a lost middle part
    r = job("zs", "touch", str(marker), cwd=repo, out=out)
    assert r.returncode == 4 and "lacks part(s) 001" in r.stderr and not marker.exists()
    (repo / "moving" / parts[1].name).write_bytes(parts[1].read_bytes())
    (repo / "moving" / parts[2].name).unlink()                    # a lost last part: only the archive's end tells
    r = job("zs", "touch", str(marker), cwd=repo, out=out)
    assert r.returncode == 4 and "incomplete or corrupt" in r.stderr and not marker.exists()
    assert not (repo / "runs" / "studies" / "paper" / "ft-metamorph-main-s9").exists()
    assert job("place", ".nothing", cwd=repo, out=out).returncode == 4
    with pytest.raises(move_runs.MoveError, match="expected runs/studies/<study>/<run>"):
        move_runs.archive_name("runs/studies/pa.per/x")


def test_a_move_sends_what_fits_back_and_the_rest_call_by_call(tmp_path):
    """A recurrent run's checkpoint (R-MeMo: 143 MiB, 10 parts) is more than one call brings back (8 files, 64 MiB):
    `move_runs.py send` moves the parts waiting in outgoing/ into $OUT in order while they fit beside what is there,
    `device_job.sh send` does so in a later call; `stage` takes the files of several calls and refuses, staging
    nothing, while a run's last part is still missing (numbering cannot tell)."""
    import os
    import sys
    from experiments import collect
    move_runs = load_tool("move_runs")
    run = tmp_path / "gpu" / "runs" / "studies" / "paper" / "ft-rmemo-main-s9"
    (run / "checkpoints" / "65").mkdir(parents=True)
    (run / "config.yaml").write_text("arch: rmemo\nseed: 9\n")
    blob = os.urandom(200_000)
    (run / "checkpoints" / "65" / "data").write_bytes(blob)
    name = move_runs.archive_name("runs/studies/paper/ft-rmemo-main-s9")
    outgoing = tmp_path / "gpu" / "outgoing"
    assert collect.main([f"runs=[{run}]", f"out={outgoing / name}", "checkpoint=true", "part_mb=0.05"]) == 0
    parts = sorted(p.name for p in outgoing.iterdir())
    assert len(parts) == 4                                           # ~200 kB of 52 kB parts
    calls = [tmp_path / f"call{k}" for k in (1, 2, 3)]
    calls[0].mkdir()
    (calls[0] / "zs.log").write_bytes(b"x" * 30_000)                 # what the call brings back already
    sent, left = move_runs.send(outgoing, calls[0], room_mib=0.15, files=8)
    assert [p.name for p in sent] == parts[:2] and [p.name for p in left] == parts[2:]   # 0.15 MiB: two parts
    sent, left = move_runs.send(outgoing, calls[1], room_mib=10, files=1)
    assert [p.name for p in sent] == parts[2:3]                       # one file slot: one part, in order
    # the defaults: 63 MiB and 8 files less what $OUT holds; from the shell, as device_job.sh's `send` call
    gpu = tmp_path / "gpu"
    r = job("send", cwd=gpu, out=calls[2])
    assert r.returncode == 0 and "sent 1 part(s)" in r.stdout and "no part left" in r.stdout, r.stdout + r.stderr
    assert sorted(p.name for p in calls[2].iterdir()) == parts[3:] and not list(outgoing.iterdir())
    r = job("send", cwd=tmp_path, out=calls[2])                       # a fresh machine: nothing packed here
    assert r.returncode == 3 and "no outgoing/" in r.stderr
    repo = tmp_path / "repo"
    repo.mkdir()

    def stage(*sources):
        return subprocess.run([sys.executable, str(SCRIPT.parent / "move_runs.py"), "stage", *map(str, sources),
                               str(repo / ".mv")], capture_output=True, text=True)
    r = stage(calls[0], calls[1])                                     # the last part still on the machine
    assert r.returncode == 4 and "end before the archive does" in r.stderr and "device_job.sh send" in r.stderr
    assert not list(repo.iterdir())
    r = stage(calls[0], calls[2])                                     # a middle part missing
    assert r.returncode == 4 and "lacks part(s) 002" in r.stderr and not list(repo.iterdir())
    r = stage(*calls)
    assert r.returncode == 0, r.stderr
    staged = sorted((repo / ".mv1").iterdir()) + sorted((repo / ".mv2").iterdir())
    assert [p.name for p in staged] == parts
    (repo / "moving").mkdir()
    for folder in (".mv1", ".mv2"):
        assert job("place", folder, cwd=repo, out=calls[2]).returncode == 0
    assert move_runs.assemble(repo / "moving", repo / "runs" / "studies")[0]
    assert (repo / "runs/studies/paper/ft-rmemo-main-s9/checkpoints/65/data").read_bytes() == blob
    # a part that came back twice with other bytes: refused
    other = tmp_path / "other"
    other.mkdir()
    (other / parts[0]).write_bytes(b"not the same")
    r = subprocess.run([sys.executable, str(SCRIPT.parent / "move_runs.py"), "stage", str(calls[0]), str(other),
                        str(tmp_path / ".mvx")], capture_output=True, text=True)
    assert r.returncode == 4 and "with other bytes" in r.stderr and not (tmp_path / ".mvx1").exists()


def test_the_move_call_packs_on_the_machine_and_sends_back_what_fits(tmp_path):
    """device_job.sh's last steps as a GPU call runs them (wheels installed, the command, the runs' artefacts, the
    cache, then DEVICE_JOB_MOVE_OUT naming two runs, as a lease of several GPUs moves them): each run's checkpoint is
    packed into outgoing/ on the machine, the first parts come back in $OUT beside the log and the runs within a
    call's 8 files, the rest wait for `send` calls, and the parts of all calls put both runs back here byte for
    byte; the call says how long its packing took, which must end within the call's 600 s."""
    import os
    import re
    move_runs = load_tool("move_runs")
    gpu = stand_in_machine(tmp_path / "gpu")
    run = gpu / "runs" / "studies" / "paper" / "ft-rmemo-main-s9"
    (run / "checkpoints" / "65").mkdir(parents=True)
    (run / "config.yaml").write_text("arch: rmemo\nseed: 9\n")
    (run / "metrics.csv").write_text("iteration\n65\n")
    blob = os.urandom(7 * 15 * 2 ** 20 + 2 ** 20)                    # 8 parts of 15 MiB: more than one call's files
    (run / "checkpoints" / "65" / "data").write_bytes(blob)
    small = gpu / "runs" / "studies" / "paper" / "ft-metamorph-main-s9"     # a second run: one part
    (small / "checkpoints" / "40").mkdir(parents=True)
    (small / "config.yaml").write_text("arch: metamorph\nseed: 9\n")
    small_blob = os.urandom(2 ** 20)
    (small / "checkpoints" / "40" / "data").write_bytes(small_blob)
    outs = [tmp_path / f"out{i}" for i in range(1, 4)]
    for o in outs:
        o.mkdir()
    env = stand_in_env(tmp_path, HOME=str(tmp_path),
                       DEVICE_JOB_MOVE_OUT="runs/studies/paper/ft-rmemo-main-s9 runs/studies/paper/ft-metamorph-main-s9")
    r = job("zs", "echo", "trained", cwd=gpu, out=outs[0], **env)
    assert r.returncode == 0 and "trained" in (outs[0] / "zs.log").read_text(), r.stdout + r.stderr
    back1 = [p for p in outs[0].iterdir() if p.name.startswith("move.")]
    assert len(back1) == 5                             # 5 of 9: the small run's and 60 MiB beside the log and runs
    assert len(list(outs[0].iterdir())) <= 8 and sum(p.stat().st_size for p in outs[0].iterdir()) <= 64 * 2 ** 20
    assert "4 part(s) left in outgoing/" in r.stdout and "1 more call(s)" in r.stdout
    assert re.search(r"zs: exit status 0; packed in \d+ s, \d+ s into the call", r.stdout), r.stdout     # timed
    assert "packed in" in (outs[0] / "zs.log").read_text().splitlines()[-1]          # in the log that comes home
    r = job("send", cwd=gpu, out=outs[1], **env)
    assert r.returncode == 0 and "sent 4 part(s)" in r.stdout and "no part left" in r.stdout, r.stdout + r.stderr
    r = job("send", cwd=gpu, out=outs[2], **env)
    assert r.returncode == 0 and "sent 0 part(s)" in r.stdout, r.stdout + r.stderr
    here = tmp_path / "here"
    here.mkdir()
    folders = move_runs.stage(outs, str(here / ".mv"))
    assert sum(len(list(f.iterdir())) for f in folders) == 9
    moving = here / "moving"
    for f in folders:
        move_runs.place(f, moving)
    back = {p.name: p for p in move_runs.assemble(moving, here / "runs" / "studies")[0]}
    assert set(back) == {"ft-rmemo-main-s9", "ft-metamorph-main-s9"}
    assert (back["ft-rmemo-main-s9"] / "checkpoints" / "65" / "data").read_bytes() == blob
    assert (back["ft-metamorph-main-s9"] / "checkpoints" / "40" / "data").read_bytes() == small_blob


def test_per_gpu_gives_each_command_its_gpu_and_ctrl_c_and_waits_for_all(tmp_path):
    """tools/per_gpu.sh: command k sees CUDA_VISIBLE_DEVICES=k, its lines come prefixed [gpu<k>]; Ctrl-C to the
    process group (device_job.sh's `timeout -s INT` at its time limit) reaches every command, which can still save,
    and the script waits for them all (a plain `a & b & wait` starts them with Ctrl-C ignored); its exit status is
    the first nonzero one."""
    import os
    import signal
    import sys
    script = SCRIPT.parent / "per_gpu.sh"
    saver = tmp_path / "saver.py"
    saver.write_text("import os, sys, time\ntry:\n    print('gpu', os.environ['CUDA_VISIBLE_DEVICES'], flush=True)\n"
                     "    time.sleep(60)\nexcept KeyboardInterrupt:\n    time.sleep(1)\n"
                     "    open(sys.argv[1], 'w').write('saved')\n    print('saved', flush=True)\n")
    # the script started as from a terminal, or with Ctrl-C ignored (as under pytest-xdist: bash cannot undo that);
    # set by a Python shim that execs it (a preexec_fn would fork this JAX process)
    shim = ("import os, signal, sys; signal.signal(signal.SIGINT, getattr(signal, sys.argv[1])); "
            "os.execvp('bash', ['bash', *sys.argv[2:]])")
    for entry in ("SIG_DFL", "SIG_IGN"):
        for name in ("a", "b"):
            (tmp_path / name).unlink(missing_ok=True)
        cmds = [f"{sys.executable} {saver} {tmp_path / name}" for name in ("a", "b")]
        p = subprocess.Popen([sys.executable, "-c", shim, entry, str(script), *cmds], stdout=subprocess.PIPE,
                             text=True, start_new_session=True)
        lines = [p.stdout.readline().strip() for _ in range(2)]       # both are running
        assert sorted(lines) == ["[gpu0] gpu 0", "[gpu1] gpu 1"]
        os.killpg(p.pid, signal.SIGINT)
        try:
            rest = p.communicate(timeout=30)[0].splitlines()
        finally:
            os.killpg(p.pid, signal.SIGKILL) if p.poll() is None else None
        assert p.returncode == 0 and sorted(rest) == ["[gpu0] saved", "[gpu1] saved"], entry
        assert (tmp_path / "a").read_text() == (tmp_path / "b").read_text() == "saved"
    r = subprocess.run(["bash", str(script), "true", "exit 5", "exit 7"], capture_output=True, text=True)
    assert r.returncode == 5
    r = subprocess.run(["bash", str(script)], capture_output=True, text=True)
    assert r.returncode == 2 and "usage: bash tools/per_gpu.sh" in r.stderr


def test_home_brings_the_last_calls_runs_each_calls_log_and_the_newest_cache(tmp_path):
    """`device_job.sh home` (tools/bring_home.py), here after a lease: the runs of the last call that packed any
    (each call packs all the machine's runs, so the last is whole), a study's runs directly in the results folder,
    each call's log as call<k>.log, the newest cache into .gpu/, runs short of their stop named and left out (no
    report may read them as finished), a run already on file not brought twice but its new evaluations added to it;
    an existing results folder is refused untouched,
    and calls that brought no run are an error that names them."""
    import tarfile
    home = load_tool("bring_home")

    def call(k: int, runs: dict[str, int], cache: bool = False) -> Path:
        c = tmp_path / f"files{k}"
        src = tmp_path / f"machine{k}"
        for run, iterations in runs.items():
            (src / run).mkdir(parents=True)
            (src / run / "config.yaml").write_text("arch: rmomo\ntotal_steps: 100000000\nstop_at: 245\n")
            (src / run / "metrics.csv").write_text("iteration\n" + "".join(f"{i}\n" for i in range(1, iterations + 1)))
        c.mkdir()
        (c / "zs.log").write_text(f"call {k}\n")
        if runs:
            with tarfile.open(c / "zs-runs.tar.gz", "w:gz") as tf:
                for top in sorted({r.split("/")[0] for r in runs}):
                    tf.add(src / top, arcname=top)
        if cache:
            (c / "xla-cache.tar.gz").write_bytes(f"cache {k}".encode())
        return c

    calls = [call(1, {"ab/ft-rmomo-s0": 50}, cache=True),
             call(2, {"ab/ft-rmomo-s0": 245, "ab/ft-rmomo-s1": 245, "ab/ft-rmomo-s3": 233}),   # s3 moved on
             call(3, {}, cache=True)]                                  # the third: a `send` call, say, with a cache
    (calls[2] / "move.ab.ft-rmomo-s2.tar.gz.000").write_bytes(b"part")
    dest, gpu = tmp_path / "results" / "ab_s51", tmp_path / ".gpu"
    done = home.bring_home(dest, calls, gpu)
    assert any(line.startswith("1 parts of moved runs came too") and f"move_runs.py stage {calls[2]} <" in line
               for line in done)
    assert sorted(p.name for p in dest.iterdir()) == ["call1.log", "call2.log", "call3.log", "ft-rmomo-s0",
                                                      "ft-rmomo-s1"]
    assert len((dest / "ft-rmomo-s0" / "metrics.csv").read_text().splitlines()) == 246      # the whole run
    assert (dest / "call2.log").read_text() == "call 2\n" and (gpu / "xla-cache.tar.gz").read_bytes() == b"cache 3"
    assert done[0].startswith(f"2 runs from {calls[1] / 'zs-runs.tar.gz'}")
    assert done[1].startswith("left out, not finished") and str(calls[1] / "zs-runs.tar.gz") in done[1]
    assert done[1].endswith(": ab/ft-rmomo-s3 (iteration 233 of 245)")
    with pytest.raises(SystemExit, match="already exists"):
        home.bring_home(dest, calls, gpu)
    assert len((dest / "ft-rmomo-s0" / "metrics.csv").read_text().splitlines()) == 246
    with pytest.raises(SystemExit, match="no <name>-runs.tar.gz in .*files3: no run came back"):
        home.bring_home(tmp_path / "results" / "other", calls[2:], gpu)
    two = call(4, {"ab/ft-rmomo-s5": 245, "cd/ft-modumorph-s0": 245, "ef/ft-metamorph-s0": 0})   # per_gpu.sh
    home.bring_home(tmp_path / "results" / "two", [two], None)
    assert (tmp_path / "results" / "two" / "ab" / "ft-rmomo-s5" / "config.yaml").exists()
    assert (tmp_path / "results" / "two" / "cd" / "ft-modumorph-s0" / "config.yaml").exists()
    assert not (tmp_path / "results" / "two" / "ef").exists()     # a study whose only run had not begun
    # two studies, one of them unfinished (session 67: R-MoMo finished, ModuMorph moved on): the finished study's
    # runs directly in the results folder, as with one study
    mixed = call(5, {"ab/ft-rmomo-s3": 245, "cd/ft-modumorph-s3": 179})
    done = home.bring_home(tmp_path / "results" / "mixed", [mixed], None)
    assert sorted(p.name for p in (tmp_path / "results" / "mixed").iterdir()) == ["call1.log", "ft-rmomo-s3"]
    assert done[1].endswith(": cd/ft-modumorph-s3 (iteration 179 of 245)")
    # a run on file already (a lease that only evaluated it, packing it beside another run): not brought twice; the
    # evaluations its copy on file lacks join that copy, those it has stay as they are
    again = call(6, {"ab/ft-rmomo-s3": 245, "cd/ft-modumorph-s4": 245})
    kept = tmp_path / "results" / "mixed" / "ft-rmomo-s3"
    (kept / "eval").mkdir()
    (kept / "eval" / "test.json").write_text("on file")
    with tarfile.open(again / "zs-runs.tar.gz", "w:gz") as tf:             # the runs again, with evaluations
        src = tmp_path / "machine6"
        (src / "ab" / "ft-rmomo-s3" / "eval").mkdir()
        (src / "ab" / "ft-rmomo-s3" / "eval" / "test.json").write_text("again")
        (src / "ab" / "ft-rmomo-s3" / "eval" / "variants.json").write_text("new")
        for top in ("ab", "cd"):
            tf.add(src / top, arcname=top)
    done = home.bring_home(tmp_path / "results" / "again", [again], None)
    assert sorted(p.name for p in (tmp_path / "results" / "again").iterdir()) == ["call1.log", "ft-modumorph-s4"]
    assert (kept / "eval" / "variants.json").read_text() == "new" and (kept / "eval" / "test.json").read_text() == \
        "on file"
    assert done[0].startswith("1 run from ") and done[0].endswith(": ft-modumorph-s4")
    assert done[1] == (f"ab/ft-rmomo-s3: already on file at {kept}, not brought again; its new evaluations added "
                       "there: variants.json")
    r = job("home", str(tmp_path / "results" / "x"), cwd=tmp_path)
    assert r.returncode == 2 and "usage: bash tools/device_job.sh home <results folder> <files_at>" in r.stderr
