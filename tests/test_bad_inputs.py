"""Bad inputs reported on one line naming the file (and element or field), with a non-zero exit and nothing
written: metadata that is not UTF-8 or has JSON `true` for an integer, robots far beyond the UNIMAL design space
(`design_space.outside_bounds`), and a MUJOCO_GL backend whose library is missing (checked before anything slow)."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from experiments import render as render_cli
from experiments import robots as cli
from mjx_morph.unimal import design_space as ds
from mjx_morph.unimal import render
from mjx_morph.unimal.errors import RobotError
from mjx_morph.unimal.mjcf import save_robot
from mjx_morph.unimal.morphology import LIMB_RADIUS
from mjx_morph.unimal.reader import load_robot
from mjx_morph.unimal.render import RenderUnavailable
from mjx_morph.unimal.sets import load_set
from mjx_morph.unimal.validate import validate_path
from mjx_morph.unimal.variants import make_variants

from test_unimal_io import small_robot

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def robot_dir(tmp_path) -> Path:
    save_robot(small_robot(), tmp_path / "robots")
    return tmp_path / "robots"


def _cli(module: str, *args: str, **env: str) -> subprocess.CompletedProcess:
    """`python -m <module> args` in the project root, with `env` added to the environment."""
    return subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, env={**os.environ, **env},
                          capture_output=True, text=True, timeout=300)


def _one_error_line(err: str) -> str:
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


# ---- metadata: UTF-8, reported once, JSON true is not an integer ---------------------------------------------

def test_non_utf8_metadata_is_a_robot_error_naming_the_file(robot_dir):
    meta = robot_dir / "metadata" / "tiny.json"
    meta.write_bytes(b'{"num_limbs": 3, "dof": 4, "symmetric_limbs": [[0, 1]], "by": "\xff\xfe"}')
    with pytest.raises(RobotError, match=r"tiny.json: not valid UTF-8 \(byte 0xff at offset \d+\)") as info:
        load_robot(robot_dir / "xml" / "tiny.xml")
    assert str(info.value).startswith(str(meta))
    assert validate_path(robot_dir).problems == [str(info.value)]


def test_non_utf8_xml_is_a_robot_error_naming_the_file(robot_dir):
    path = robot_dir / "xml" / "tiny.xml"
    path.write_bytes(path.read_bytes().replace(b"<worldbody>", b"<worldbody>\xff", 1))
    with pytest.raises(RobotError, match=r"tiny.xml: not valid UTF-8 \(byte 0xff at offset \d+\)"):
        load_robot(path)


def test_cli_validate_non_utf8_metadata(robot_dir, capsys):
    (robot_dir / "metadata" / "tiny.json").write_bytes(b'{"num_limbs": \xff 3}')
    assert cli.main(["validate", str(robot_dir)]) == 1
    out = capsys.readouterr()
    assert out.out.splitlines() == [f"{robot_dir / 'metadata' / 'tiny.json'}: not valid UTF-8 (byte 0xff at offset "
                                    f"14); expected a UTF-8 JSON file"]
    assert "Traceback" not in out.err


def test_run_cli_non_utf8_metadata_names_the_file_and_writes_nothing(robot_dir, tmp_path):
    (robot_dir / "metadata" / "tiny.json").write_bytes(b'{"num_limbs": \xff 3}')
    run_dir = tmp_path / "run"
    r = _cli("experiments.run", f"robots={robot_dir}", f"run_dir={run_dir}", "preset=smoke", "progress=false",
             "compile_cache=null")
    assert r.returncode == 2, r.stderr
    assert _one_error_line(r.stderr) == f"error: {robot_dir / 'metadata' / 'tiny.json'}: not valid UTF-8 (byte 0xff " \
                                        f"at offset 14); expected a UTF-8 JSON file"
    assert not run_dir.exists()


def test_malformed_metadata_is_reported_once(robot_dir, capsys):
    (robot_dir / "metadata" / "tiny.json").write_text("{not json")
    problems = validate_path(robot_dir).problems
    assert len(problems) == 1 and "tiny.json: malformed JSON" in problems[0]
    assert cli.main(["validate", str(robot_dir)]) == 1
    assert len(capsys.readouterr().out.splitlines()) == 1


@pytest.mark.parametrize("meta,message", [
    ({"num_limbs": True, "dof": 4}, r'"num_limbs": expected an integer, got true'),
    ({"num_limbs": 3, "dof": False}, r'"dof": expected an integer, got false'),
    ({"num_limbs": 3, "dof": 4.0}, r'"dof": expected an integer, got 4.0'),
    ({"num_limbs": 3, "dof": 4, "symmetric_limbs": [[True, 1]]},
     r'"symmetric_limbs": expected a list of \[int, int\] limb-id pairs, got \[\[true, 1\]\]'),
])
def test_json_booleans_are_not_integers(robot_dir, meta, message):
    path = robot_dir / "metadata" / "tiny.json"
    path.write_text(json.dumps(meta))
    with pytest.raises(RobotError, match=message) as info:
        load_robot(robot_dir / "xml" / "tiny.xml")
    assert str(info.value).startswith(f"{path}: ")


# ---- robots far beyond the design space -------------------------------------------------------------------------

def _scale_limb(m, index: int, factor: float):
    limbs = list(m.limbs)
    limbs[index] = dataclasses.replace(limbs[index], tip=tuple(factor * v for v in limbs[index].tip))
    return dataclasses.replace(m, limbs=tuple(limbs))


def _all_joints(m, **changes):
    return dataclasses.replace(m, limbs=tuple(dataclasses.replace(
        l, joints=tuple(dataclasses.replace(j, **changes) for j in l.joints)) for l in m.limbs))


OUTSIDE = [
    ("long_limb", lambda m: _scale_limb(m, 1, 50 / 0.35),
     r'<body name="limb/2">: capsule length 50 m is outside the UNIMAL design space; expected 0.05 to 2 m'),
    ("huge_gear_tiny_density", lambda m: dataclasses.replace(_all_joints(m, gear=1e6), torso_density=1e-6),
     r'<body name="torso/0">: density 1e-06 kg/m\^3 is outside the UNIMAL design space; expected 100 to 5000'),
    ("huge_gear", lambda m: _all_joints(m, gear=1e6),
     r'<motor joint="limbx/0">: gear 1e\+06 is outside the UNIMAL design space; expected 30 to 1500'),
    ("wide_range", lambda m: _all_joints(m, range=(-170.0, 170.0)),
     r'<joint name="limbx/0">: range \(-170, 170\) degrees is outside the UNIMAL design space'),
    ("fat_limb", lambda m: dataclasses.replace(m, limbs=(dataclasses.replace(m.limbs[0], radius=1.0),) + m.limbs[1:]),
     r'<body name="limb/0">: capsule radius 1 m is outside the UNIMAL design space; expected 0.01 to 0.25 m'),
]


@pytest.mark.parametrize("case,edit,message", OUTSIDE, ids=[c[0] for c in OUTSIDE])
def test_outside_design_space_is_refused_when_loading(tmp_path, case, edit, message):
    m = edit(small_robot())
    save_robot(m, tmp_path)
    path = tmp_path / "xml" / "tiny.xml"
    with pytest.raises(RobotError, match=message) as info:
        load_robot(path)
    assert str(info.value).startswith(f"{path}: <")
    with pytest.raises(RobotError, match=message):
        load_set(str(tmp_path))
    assert load_robot(path, allow_outside_design_space=True) == m
    assert len(load_set(str(tmp_path), allow_outside_design_space=True)) == 1
    # a training run refuses them too, unless its config accepts them
    from mjx_morph.run import compose_run_config, train_robots
    with pytest.raises(RobotError, match=message):
        train_robots(compose_run_config([f"robots={tmp_path}"]))
    assert train_robots(compose_run_config([f"robots={tmp_path}", "allow_outside_design_space=true"]))[1] == (m,)


def test_cli_validate_outside_design_space_errors_or_warns_with_the_flag(tmp_path, capsys):
    m = dataclasses.replace(_all_joints(small_robot(), gear=1e6), torso_density=1e-6)
    save_robot(m, tmp_path)
    assert cli.main(["validate", str(tmp_path)]) == 1
    out = capsys.readouterr()
    lines = out.out.splitlines()
    assert len(lines) == 5 and all(l.startswith(str(tmp_path / "xml" / "tiny.xml") + ": <") for l in lines)
    assert sum("gear 1e+06" in l for l in lines) == 4 and "torso/0" in lines[0]
    assert "5 problem(s)" in out.err and "--allow-outside-design-space" in out.err

    assert cli.main(["validate", str(tmp_path), "--allow-outside-design-space"]) == 0
    out = capsys.readouterr()
    warnings = [l for l in out.out.splitlines() if l.startswith("warning: ")]
    assert [w.removeprefix("warning: ") for w in warnings] == lines
    assert out.out.splitlines()[-1] == f"{tmp_path}: ok (5 warning(s))"

    assert cli.main(["info", str(tmp_path)]) == 2
    assert _one_error_line(capsys.readouterr().err).startswith(f"error: {tmp_path / 'xml' / 'tiny.xml'}: <")
    assert cli.main(["info", str(tmp_path), "--allow-outside-design-space"]) == 0


def test_meaningless_value_is_reported_once(tmp_path):
    m = small_robot()
    leg = m.limbs[1]
    m = dataclasses.replace(m, limbs=(m.limbs[0], dataclasses.replace(
        leg, joints=(dataclasses.replace(leg.joints[0], gear=-5.0), leg.joints[1])), m.limbs[2]))
    save_robot(m, tmp_path)
    path = tmp_path / "xml" / "tiny.xml"
    assert validate_path(tmp_path).problems == [f"{path}: limbx/2: gear -5.0 must be positive"]
    with pytest.raises(RobotError, match=r'<motor joint="limbx/2">: gear -5 is outside the UNIMAL design space'):
        load_robot(path)


def test_bounds_are_generous_around_the_design_space():
    lengths = [LIMB_RADIUS + h for h in ds.LIMB_HEIGHTS]                      # r + h
    assert ds.LIMB_LENGTH_BOUNDS[0] * 4 < min(lengths) and max(lengths) * 4 < ds.LIMB_LENGTH_BOUNDS[1]
    for values, (lo, hi) in ((ds.DENSITIES, ds.DENSITY_BOUNDS), (ds.GEARS, ds.GEAR_BOUNDS)):
        assert lo * 4 < min(values) and max(values) * 4 < hi
    assert all(-ds.JOINT_LIMIT_MAX < lo < hi < ds.JOINT_LIMIT_MAX and hi - lo > 4 * ds.JOINT_SPAN_MIN
               for lo, hi in ds.JOINT_RANGES)


@pytest.mark.parametrize("name", ["gen/train", "gen/test"])
def test_shipped_sets_and_variants_are_inside_the_bounds(name):
    rs = load_set(name)                                   # refuses a robot outside the bounds
    assert len(rs) == 100 and all(ds.outside_bounds(m) == [] for m in rs.robots)
    assert validate_path(rs.source) == ([], [], [])
    variants = make_variants(rs.robots[:3])               # every change type, 4 each
    assert all(ds.outside_bounds(v) == [] for v in variants)


@pytest.mark.parametrize("split", ["train", "test", "val", "test70"])
def test_original_robots_are_inside_the_bounds(unimals, split):
    rs = load_set(f"unimal100/{split}")                   # refuses a robot outside the bounds
    assert len(rs) == {"train": 100, "test": 102, "val": 32, "test70": 70}[split]
    assert all(ds.outside_bounds(m) == [] for m in rs.robots)
    if split in ("train", "test"):
        assert validate_path(unimals / split) == ([], [], [])


# ---- no OpenGL backend: a one-line error before anything slow ----------------------------------------------------

needs_no_osmesa = pytest.mark.skipif(render.backend_library("osmesa") is not None,
                                     reason="libOSMesa is installed on this machine")


@needs_no_osmesa
def test_render_cli_without_osmesa_exits_2_before_loading_the_run(tmp_path):
    r = _cli("experiments.render", f"run_dir={tmp_path / 'no-such-run'}", "robot=gen-0-5", MUJOCO_GL="osmesa")
    assert r.returncode == 2, r.stderr
    line = _one_error_line(r.stderr)
    assert line.startswith("error: no OpenGL backend for offscreen rendering (MUJOCO_GL=osmesa")
    assert "libOSMesa is not installed" in line and "apt-get install libosmesa6" in line


@needs_no_osmesa
def test_robots_cli_without_osmesa(tmp_path):
    out = tmp_path / "g.png"
    r = _cli("experiments.robots", "gallery", "gen/train", "--out", str(out), "--max", "2", MUJOCO_GL="osmesa")
    assert r.returncode == 2 and not out.exists(), r.stderr
    assert _one_error_line(r.stderr).startswith("error: no OpenGL backend")
    r = _cli("experiments.robots", "info", "gen/train", MUJOCO_GL="osmesa")   # no rendering: works as before
    assert r.returncode == 0 and "100 robots" in r.stdout, r.stderr


def test_render_checks_gl_before_loading_the_run(tmp_path, monkeypatch, capsys):
    def no_gl(*_):
        raise RenderUnavailable("no OpenGL backend for offscreen rendering (test)")

    def load_run(*_):
        raise AssertionError("the run was loaded before the OpenGL check")
    monkeypatch.setattr(render, "gl_context", no_gl)
    monkeypatch.setattr(render_cli, "load_run", load_run)
    assert render_cli.main([f"run_dir={tmp_path}", "robot=gen-0-5"]) == 2
    assert _one_error_line(capsys.readouterr().err) == "error: no OpenGL backend for offscreen rendering (test)"
    assert cli.main(["gallery", "no/such/set", "--out", str(tmp_path / "g.png")]) == 2
    assert _one_error_line(capsys.readouterr().err) == "error: no OpenGL backend for offscreen rendering (test)"
