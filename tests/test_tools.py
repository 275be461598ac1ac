"""tools/device_job.sh, the wrapper of a command on a lent GPU machine: the checks that run before anything is
installed (the machine's wheels and GPU are not here)."""
import subprocess
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "tools" / "device_job.sh"


def job(*args, cwd, out=None, **extra_env):
    env = {"PATH": "/usr/bin:/bin", **({"OUT": str(out)} if out else {}), **extra_env}
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=cwd, env=env, capture_output=True, text=True)


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
