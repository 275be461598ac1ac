"""Reading, validating and writing UNIMAL robot files; robot sets; the robots CLI."""
from __future__ import annotations

import json
import re
from pathlib import Path

import mujoco
import numpy as np
import pytest

from experiments import robots as cli
from mjx_morph.unimal.errors import RobotError
from mjx_morph.unimal.mjcf import compile_model, save_robot, to_mjcf
from mjx_morph.unimal.morphology import TORSO, Joint, Limb, Morphology
from mjx_morph.unimal.reader import load_folder, load_robot
from mjx_morph.unimal.sets import load_set, split_test
from mjx_morph.unimal.validate import check_morphology, validate_path

COMPARED = ("body_mass", "body_inertia", "body_pos", "body_ipos", "body_iquat", "jnt_axis", "jnt_range", "jnt_pos",
            "actuator_gear", "geom_size", "geom_pos", "geom_quat", "dof_armature", "dof_damping", "jnt_stiffness")


def small_robot(name: str = "tiny") -> Morphology:
    """Torso, a mirror pair of horizontal limbs with one hinge each, and a two-hinge leg below the first."""
    jy = Joint("y", (-0.05, 0.0, 0.0), (0.0, 1.0, 0.0), (-30.0, 30.0), 200.0)
    left = Limb(id=0, parent=TORSO, pos=(0.0, 0.1, 0.0), tip=(0.0, 0.25, 0.0), density=700.0,
                joints=(Joint("x", (0.0, -0.05, 0.0), (0.0, 0.0, 1.0), (-45.0, 45.0), 150.0),))
    right = Limb(id=1, parent=TORSO, pos=(0.0, -0.1, 0.0), tip=(0.0, -0.25, 0.0), density=700.0,
                 joints=(Joint("x", (0.0, 0.05, 0.0), (0.0, 0.0, -1.0), (-45.0, 45.0), 150.0),))
    leg = Limb(id=2, parent=0, pos=(0.0, 0.25, -0.05), tip=(0.0, 0.0, -0.35), density=700.0,
               joints=(Joint("x", (0.0, 0.0, 0.05), (1.0, 0.0, 0.0), (-60.0, 0.0), 250.0), jy))
    return Morphology(name=name, height=0.6, limbs=(left, leg, right), torso_density=800.0, mirror_pairs=((0, 1),))


@pytest.fixture()
def robot_dir(tmp_path) -> Path:
    save_robot(small_robot(), tmp_path)
    return tmp_path


def _compare(a: mujoco.MjModel, b: mujoco.MjModel, tol: float = 1e-6) -> float:
    worst = 0.0
    for f in COMPARED:
        x, y = getattr(a, f), getattr(b, f)
        assert x.shape == y.shape, f
        worst = max(worst, float(np.abs(x - y).max(initial=0.0)))
    return worst


# ---- round trips -------------------------------------------------------------------------------------------

def test_written_robot_reads_back_identically(robot_dir):
    m = small_robot()
    back = load_robot(robot_dir / "xml" / "tiny.xml")
    assert back == m
    assert m.num_limbs == 3 and m.dof == 4 and m.tree_depth == 2
    np.testing.assert_allclose(compile_model(m).body_mass.sum(), m.total_mass, rtol=1e-9)
    meta = json.loads((robot_dir / "metadata" / "tiny.json").read_text())
    assert meta == {"symmetric_limbs": [[0, 1]], "dof": 4, "num_limbs": 3}


@pytest.mark.parametrize("split", ["train", "test"])
def test_all_original_robots_read_validate_and_round_trip(unimals, split):
    robots = load_folder(unimals / split)
    assert len(robots) == {"train": 100, "test": 102}[split]
    worst = 0.0
    for m in robots:
        assert check_morphology(m) == []
        assert m.num_limbs <= 10 and all(len(l.joints) <= 2 for l in m.limbs)
        original = mujoco.MjModel.from_xml_path(str(unimals / split / "xml" / f"{m.name}.xml"))
        worst = max(worst, _compare(original, mujoco.MjModel.from_xml_string(to_mjcf(m))))   # the file as written
        # joints and motors come out in the original order, so policy tokens follow the file's body order
        assert [original.joint(i).name for i in range(1, original.njnt)] == \
               [f"limb{j.kind}/{m.limbs[i].id}" for i, j in m.joints()]
    assert worst <= 1e-6


def test_compiled_limbs_have_metamorphs_masses(unimals):
    """The simulation compiles limbs with the mass and inertia MetaMorph's MuJoCo 2.0 gave them (a cylinder over
    the segment plus one radius; current MuJoCo counts the hemispherical caps): the lightest train limb then
    weighs ModuMorph's stored lower bound of the body-mass context feature, 1.17809725 (MuJoCo 4 alone: 1.2435),
    and each limb body's inertia is that cylinder's about the capsule's centre."""
    robots = load_set("unimal100/train").robots
    lightest = min((l for m in robots for l in m.limbs), key=lambda l: l.mass)
    np.testing.assert_allclose(lightest.mass, 1.17809725, rtol=1e-8)
    m = max(robots, key=lambda m: m.num_limbs)
    mm, exact = compile_model(m), mujoco.MjModel.from_xml_string(to_mjcf(m))
    for l in m.limbs:
        b = mujoco.mj_name2id(mm, mujoco.mjtObj.mjOBJ_BODY, l.name)
        np.testing.assert_allclose(mm.body_mass[b], l.mass, rtol=1e-12)
        assert 1.03 < exact.body_mass[b] / mm.body_mass[b] < 1.06, l.name     # MuJoCo 4's own: 3-5% heavier
        np.testing.assert_allclose(mm.body_ipos[b], np.asarray(l.tip) / 2, atol=1e-12)
        r, h = l.radius, l.length + l.radius
        want = l.mass * np.array([(3 * r * r + h * h) / 12, (3 * r * r + h * h) / 12, r * r / 2])
        np.testing.assert_allclose(mm.body_inertia[b], want, rtol=1e-9)
    np.testing.assert_allclose(mm.body_mass.sum(), m.total_mass, rtol=1e-12)


def test_compiled_limbs_keep_the_capsules_inertial_frame(unimals):
    """Every limb body's inertial frame is its capsule's frame, as MuJoCo frames a body of one geom (body_iquat and
    body_ipos of the file compiled alone; every other compared field is the file's too, exactly), so the context
    stays inside ModuMorph's fixed bounds: all 35 features of every train and test robot in [-1, 1]. Two principal
    moments are equal, so a `fullinertia` lets the compiler pick any frame in their plane: it did for 566 of the
    807 train limbs (iquat (0.5, 0.5, 0.5, 0.5), say), a 4th component whose bounds are both 0, hence contexts up
    to 1e8 (session 44's R-MeMo run started from values of 1e5 and never learnt; `sim.model` now refuses such a
    context)."""
    import sim_reference as ref
    worst, ctx = 0.0, 0.0
    for split in ("train", "test"):
        for m in load_set(f"unimal100/{split}").robots:
            mm, own = compile_model(m), mujoco.MjModel.from_xml_string(to_mjcf(m))
            for f in set(COMPARED) - {"body_mass", "body_inertia"}:     # all but what the <inertial> sets
                worst = max(worst, float(np.abs(getattr(mm, f) - getattr(own, f)).max()))
            ctx = max(ctx, float(np.abs(ref.context(mm)).max()))
    assert worst <= 1e-12
    assert ctx <= 1.0 + 1e-6


def test_original_sets_and_split(unimals):
    test = load_set("unimal100/test")
    val, test70 = load_set("unimal100/val"), load_set("unimal100/test70")
    assert (len(val), len(test70)) == (32, 70)
    assert set(val.names).isdisjoint(test70.names)
    assert set(val.names) | set(test70.names) == set(test.names)
    assert split_test(test.names) == split_test(list(reversed(test.names)))  # order-independent, fixed


# ---- bad input: one clear error naming file, element and expectation -------------------------------------

BAD_XML = [
    ("malformed", lambda s: s.replace("</worldbody>", ""), r"malformed XML"),
    ("not_mjcf", lambda s: s.replace("<mujoco ", "<robot ").replace("</mujoco>", "</robot>"), r"root element <mujoco>"),
    ("no_torso", lambda s: s.replace('name="torso/0" pos', 'name="body0" pos'), r'no body named "torso/0"'),
    ("box_geom", lambda s: s.replace('<geom name="limb/2" ', '<geom name="limb/2" type="box" '),
     r'<geom name="limb/2">: type "box" is not allowed; expected "capsule"'),
    ("ball_joint", lambda s: s.replace('<joint name="limbx/1" ', '<joint name="limbx/1" type="ball" '),
     r'<joint name="limbx/1">: type "ball" is not allowed'),
    ("slide_joint", lambda s: s.replace('<joint name="limbx/0" ', '<joint name="limbx/0" type="slide" '),
     r'<joint name="limbx/0">: type "slide" is not allowed'),
    ("three_joints", lambda s: s.replace('<geom name="limb/2"', '<joint name="limby/2" range="0 1"/><geom name="limb/2"'),
     r'<body name="limb/2">: 3 joints; a UNIMAL limb has at most 2'),
    ("missing_motor", lambda s: re.sub(r'<motor name="limby/2"[^>]*/>', "", s), r"missing motor for joint\(s\) limby/2"),
    ("rotated_body", lambda s: s.replace('<body name="limb/1" ', '<body name="limb/1" euler="0 0 90" '),
     r'<body name="limb/1">: attribute "euler": UNIMAL bodies are never rotated'),
    ("bad_number", lambda s: s.replace('range="-60 0"', 'range="-60 abc"'), r'range="-60 abc" is not a list of numbers'),
    ("second_geom", lambda s: s.replace('<geom name="limb/0" ', '<geom type="sphere" size="0.1"/><geom name="limb/0" '),
     r'<body name="limb/0">: expected exactly one capsule geom, found 2'),
    ("capsule_torso", lambda s: s.replace('<geom name="torso/0" type="sphere" size="0.1"',
                                          '<geom name="torso/0" type="capsule" fromto="0 0 0 0.1 0 0" size="0.1"'),
     r'<geom name="torso/0">: type "capsule" is not allowed; expected "sphere"'),
    ("no_torso_geom", lambda s: re.sub(r'<geom name="torso/0"[^>]*/>', "", s),
     r'<body name="torso/0">: expected exactly one sphere geom, found 0'),
]


@pytest.mark.parametrize("case,edit,message", BAD_XML, ids=[c[0] for c in BAD_XML])
def test_bad_robot_file_gives_clear_error(robot_dir, case, edit, message):
    path = robot_dir / "xml" / "tiny.xml"
    path.write_text(edit(path.read_text()))
    with pytest.raises(RobotError, match=message) as info:
        load_robot(path)
    assert str(path) in str(info.value)
    assert validate_path(robot_dir).problems == [str(info.value)]


def test_too_many_limbs(tmp_path):
    joint = small_robot().limbs[0].joints
    limbs = tuple(Limb(id=i, parent=i - 1 if i else TORSO, pos=(0.0, 0.25 if i else 0.1, 0.0), tip=(0.0, 0.2, 0.0),
                       joints=joint) for i in range(11))
    m = Morphology(name="long", height=0.6, limbs=limbs)
    (tmp_path / "long.xml").write_text(to_mjcf(m))  # well formed, but 11 limbs
    with pytest.raises(RobotError, match=r"long.xml: <body name=\"torso/0\">: 11 limbs; the UNIMAL design space allows at most 10"):
        load_robot(tmp_path / "long.xml")
    assert any("11 limbs" in p for p in check_morphology(m))


@pytest.mark.parametrize("meta,message", [
    ({"num_limbs": 4, "dof": 4, "symmetric_limbs": []}, r'"num_limbs": says 4 but .* has 3 limbs'),
    ({"num_limbs": 3, "dof": 5, "symmetric_limbs": []}, r'"dof": says 5 but .* has 4 hinge joints'),
    ({"num_limbs": 3, "dof": 4, "symmetric_limbs": [[0, 7]]}, r'"symmetric_limbs": limb id 7 does not exist'),
    ({"num_limbs": "3", "dof": 4}, r'"num_limbs": expected an integer, got "3"'),
    ({"num_limbs": 3}, r'"dof": missing; expected an integer'),
])
def test_metadata_contradicting_xml(robot_dir, meta, message):
    meta_path = robot_dir / "metadata" / "tiny.json"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(RobotError, match=message) as info:
        load_robot(robot_dir / "xml" / "tiny.xml")
    assert str(meta_path) in str(info.value)


def test_malformed_metadata(robot_dir):
    (robot_dir / "metadata" / "tiny.json").write_text("{not json")
    with pytest.raises(RobotError, match=r"tiny.json: malformed JSON"):
        load_robot(robot_dir / "xml" / "tiny.xml")


def test_limbs_must_be_in_mujoco_body_order():
    m = small_robot()
    shuffled = Morphology(**{**m.__dict__, "limbs": (m.limbs[0], m.limbs[2], Limb(**{**m.limbs[1].__dict__}))})
    assert any("depth-first" in p for p in check_morphology(shuffled))


def test_unknown_set_and_missing_path():
    with pytest.raises(RobotError, match="not a robot set or path; known sets"):
        load_set("nowhere/nothing")


# ---- the CLI -------------------------------------------------------------------------------------------------

def test_cli_info_validate_export(robot_dir, tmp_path, capsys):
    assert cli.main(["info", str(robot_dir)]) == 0
    out = capsys.readouterr().out
    assert "tiny" in out and "1 robots" in out
    assert cli.main(["validate", str(robot_dir)]) == 0
    assert cli.main(["export", str(robot_dir / "xml" / "tiny.xml"), "--out", str(tmp_path / "t.xml")]) == 0
    exported = mujoco.MjModel.from_xml_path(str(tmp_path / "t.xml"))
    assert exported.nu == 4 and exported.nbody == 5


def test_cli_user_errors_exit_nonzero_without_traceback(robot_dir, capsys):
    path = robot_dir / "xml" / "tiny.xml"
    path.write_text(path.read_text().replace('<geom name="limb/2" ', '<geom name="limb/2" type="box" '))
    assert cli.main(["validate", str(robot_dir)]) == 1
    out = capsys.readouterr()
    assert 'type "box" is not allowed' in out.out and "Traceback" not in out.out + out.err
    assert cli.main(["info", str(robot_dir)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "tiny.xml" in err and "Traceback" not in err


def test_cli_gallery(robot_dir, tmp_path):
    from mjx_morph.unimal.render import RenderUnavailable, render_robots
    try:
        images = render_robots([small_robot()], size=64)
    except RenderUnavailable as e:
        pytest.skip(str(e))
    assert images[0].shape == (64, 64, 3) and images[0].std() > 1  # not a blank image
    assert cli.main(["gallery", str(robot_dir), "--out", str(tmp_path / "g.png"), "--size", "64"]) == 0
    assert (tmp_path / "g.png").stat().st_size > 1000
