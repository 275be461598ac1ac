"""Read MetaMorph-format UNIMAL robots into `Morphology` values, validating while reading.

A robot is either a single MJCF file (DERL/MetaMorph template) or an entry of a folder with `xml/<id>.xml` and
`metadata/<id>.json`. Everything outside the UNIMAL format raises `RobotError` naming the file, the element and
what was expected; so does a robot with values far beyond the design space (`design_space.outside_bounds`), unless
the caller allows it. Only the robot (`torso/0` subtree) and its motors are read; sensors, sites, cameras, lights,
assets and `<contact>` excludes are ignored, as MetaMorph does when it builds its envs.
"""
from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .design_space import outside_bounds
from .errors import RobotError
from .morphology import MAX_JOINTS_PER_LIMB, MAX_LIMBS, TORSO, Joint, Limb, Morphology

_LIMB_RE = re.compile(r"^limb/(\d+)$")
_JOINT_RE = re.compile(r"^limb([xy])/(\d+)$")
# MuJoCo's built-in joint defaults for the attributes we read (used when neither the element nor a class sets them).
_MUJOCO_JOINT_DEFAULTS = {"type": "hinge", "armature": "0", "damping": "0", "stiffness": "0", "limited": "auto"}
_GEOM_DEFAULTS = {"type": "sphere", "density": "1000"}


def _tag(el: ET.Element) -> str:
    name = el.get("name")
    return f'<{el.tag} name="{name}">' if name is not None else f"<{el.tag}>"


def _floats(where: str, el: ET.Element, attr: str, n: int | tuple[int, ...], value: str | None = None) -> tuple[float, ...]:
    text = el.get(attr) if value is None else value
    if text is None:
        raise RobotError(where, _tag(el), f'attribute "{attr}" is missing')
    try:
        vals = tuple(float(t) for t in text.split())
    except ValueError:
        raise RobotError(where, _tag(el), f'attribute {attr}="{text}" is not a list of numbers') from None
    ns = (n,) if isinstance(n, int) else n
    if len(vals) not in ns or not all(math.isfinite(v) for v in vals):
        want = " or ".join(str(k) for k in ns)
        raise RobotError(where, _tag(el), f'attribute {attr}="{text}": expected {want} finite numbers')
    return vals


class _Defaults:
    """The `<default>` classes of one file, flattened (child classes inherit from their parents)."""

    def __init__(self, root: ET.Element):
        self.classes: dict[str, dict[str, dict[str, str]]] = {}
        top = root.find("default")
        self.main: dict[str, dict[str, str]] = {}
        if top is not None:
            self._walk(top, {}, is_main=True)

    def _walk(self, el: ET.Element, inherited: dict[str, dict[str, str]], is_main: bool = False) -> None:
        own = {k: dict(v) for k, v in inherited.items()}
        for child in el:
            if child.tag != "default":
                own.setdefault(child.tag, {}).update(child.attrib)
        if is_main:
            self.main = own
        else:
            self.classes[el.get("class", "")] = own
        for child in el:
            if child.tag == "default":
                self._walk(child, own)

    def resolve(self, el: ET.Element, builtin: dict[str, str]) -> dict[str, str]:
        attrs = dict(builtin)
        cls = el.get("class")
        attrs.update((self.classes.get(cls, self.main) if cls is not None else self.main).get(el.tag, {}))
        attrs.update(el.attrib)
        return attrs


def read_metadata(path: Path) -> dict:
    """The MetaMorph metadata JSON: num_limbs, dof, symmetric_limbs (integers; JSON `true`/`false` are refused)."""
    where = str(path)
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise RobotError(where, "", f"not valid UTF-8 ({_bad_byte(e)}); expected a UTF-8 JSON file") from None
    except OSError as e:
        raise RobotError(where, "", f"cannot be read ({e.strerror or e})") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise RobotError(where, "", f"malformed JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(meta, dict):
        raise RobotError(where, "", "expected a JSON object with keys num_limbs, dof, symmetric_limbs")
    for key in ("num_limbs", "dof"):
        if key not in meta:
            raise RobotError(where, f'"{key}"', "missing; expected an integer")
        if not _is_int(meta[key]):
            raise RobotError(where, f'"{key}"', f"expected an integer, got {_short(json.dumps(meta[key]))}")
    pairs = meta.get("symmetric_limbs", [])
    if not isinstance(pairs, list) or not all(
            isinstance(p, list) and len(p) == 2 and all(_is_int(i) for i in p) for p in pairs):
        raise RobotError(where, '"symmetric_limbs"', "expected a list of [int, int] limb-id pairs, got "
                         + _short(json.dumps(pairs)))
    return meta


def _bad_byte(e: UnicodeDecodeError) -> str:
    return f"byte 0x{e.object[e.start]:02x} at offset {e.start}"


def _is_int(value) -> bool:
    """A JSON integer; `bool` is a subclass of `int` in Python, but JSON `true` is not a number."""
    return isinstance(value, int) and not isinstance(value, bool)


def _short(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def load_robot(xml_path: str | Path, metadata_path: str | Path | None = None, name: str | None = None, *,
               allow_outside_design_space: bool = False) -> Morphology:
    """Read and validate one robot file. If `metadata_path` is None, a sibling `../metadata/<id>.json` is used
    when it exists (MetaMorph layout); without metadata the robot has no mirror pairs. A robot with values beyond
    the plausibility bounds of `design_space.outside_bounds` (a 50 m limb, a gear of 1e6) raises `RobotError` for
    the first of them, unless `allow_outside_design_space`."""
    xml_path = Path(xml_path)
    where = str(xml_path)
    if not xml_path.is_file():
        raise RobotError(where, "", "no such file")
    if metadata_path is None:
        candidate = xml_path.parent.parent / "metadata" / (xml_path.stem + ".json")
        metadata_path = candidate if candidate.is_file() else None
    try:
        data = xml_path.read_bytes()
    except OSError as e:
        raise RobotError(where, "", f"cannot be read ({e.strerror or e})") from None
    try:
        root = ET.fromstring(data)
    except ET.ParseError as e:
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as u:
            raise RobotError(where, "", f"not valid UTF-8 ({_bad_byte(u)}); expected a UTF-8 MJCF file") from None
        raise RobotError(where, "", f"malformed XML ({e})") from None
    if root.tag != "mujoco":
        raise RobotError(where, f"<{root.tag}>", "expected an MJCF file with root element <mujoco>")
    compiler = root.find("compiler")
    degrees = compiler is None or compiler.get("angle", "degree") == "degree"
    defaults = _Defaults(root)

    torso = None
    for body in root.iter("body"):
        if body.get("name") == "torso/0":
            torso = body
            break
    if torso is None:
        raise RobotError(where, "<worldbody>", 'no body named "torso/0"; not a UNIMAL robot')
    for body in root.iter("body"):
        body_name = body.get("name", "")
        if body_name.startswith("torso/") and body_name != "torso/0":
            raise RobotError(where, _tag(body), "UNIMAL robots have exactly one torso, torso/0")

    torso_pos = _floats(where, torso, "pos", 3, torso.get("pos", "0 0 0"))
    if abs(torso_pos[0]) > 1e-9 or abs(torso_pos[1]) > 1e-9:
        raise RobotError(where, _tag(torso), f'pos="{torso.get("pos")}": expected the torso at x = y = 0')
    _check_no_rotation(where, torso)
    tjoints = torso.findall("joint") + torso.findall("freejoint")
    if len(tjoints) != 1 or not (tjoints[0].tag == "freejoint" or defaults.resolve(tjoints[0], {"type": "hinge"})["type"] == "free"):
        raise RobotError(where, _tag(torso), "expected exactly one free joint on the torso")
    tgeom, tg = _one_geom(where, torso, "sphere", defaults)
    torso_radius = _floats(where, tgeom, "size", (1, 2, 3), tg.get("size"))[0]
    torso_density = _positive(where, tgeom, "density", tg["density"])

    limbs: list[Limb] = []
    limb_elems: list[ET.Element] = []

    def visit(body: ET.Element, parent: int) -> None:
        for child in body.findall("body"):
            limbs.append(_read_limb(where, child, parent, defaults, degrees))
            limb_elems.append(child)
            visit(child, len(limbs) - 1)

    visit(torso, TORSO)
    if not limbs:
        raise RobotError(where, _tag(torso), "the robot has no limbs")
    if len(limbs) > MAX_LIMBS:
        raise RobotError(where, _tag(torso), f"{len(limbs)} limbs; the UNIMAL design space allows at most {MAX_LIMBS}")
    ids = [l.id for l in limbs]
    if len(set(ids)) != len(ids):
        raise RobotError(where, "<body>", f"duplicate limb ids in {ids}")

    limbs = _read_motors(where, root, limbs)

    pairs: tuple[tuple[int, int], ...] = ()
    if metadata_path is not None:
        meta = read_metadata(Path(metadata_path))
        mw = str(metadata_path)
        if meta["num_limbs"] != len(limbs):
            raise RobotError(mw, '"num_limbs"', f"says {meta['num_limbs']} but {where} has {len(limbs)} limbs")
        dof = sum(len(l.joints) for l in limbs)
        if meta["dof"] != dof:
            raise RobotError(mw, '"dof"', f"says {meta['dof']} but {where} has {dof} hinge joints")
        for a, b in meta.get("symmetric_limbs", []):
            for i in (a, b):
                if i not in ids:
                    raise RobotError(mw, '"symmetric_limbs"', f"limb id {i} does not exist in {where}")
        pairs = tuple((int(a), int(b)) for a, b in meta.get("symmetric_limbs", []))

    m = Morphology(name=name or xml_path.stem, height=float(torso_pos[2]), limbs=tuple(limbs),
                   torso_density=torso_density, torso_radius=float(torso_radius), mirror_pairs=pairs)
    beyond = [] if allow_outside_design_space else outside_bounds(m)
    if beyond:
        raise RobotError(where, *beyond[0])
    return m


def _positive(where: str, el: ET.Element, attr: str, text: str) -> float:
    v = _floats(where, el, attr, 1, text)[0]
    if v <= 0:
        raise RobotError(where, _tag(el), f'{attr}="{text}": expected a positive number')
    return v


def _check_no_rotation(where: str, body: ET.Element) -> None:
    for attr in ("quat", "euler", "axisangle", "xyaxes", "zaxis"):
        if body.get(attr) is not None:
            raise RobotError(where, _tag(body), f'attribute "{attr}": UNIMAL bodies are never rotated')


def _one_geom(where: str, body: ET.Element, kind: str, defaults: _Defaults) -> tuple[ET.Element, dict]:
    """The body's single geom and its resolved attributes; an error unless there is exactly one, of type `kind`."""
    geoms = body.findall("geom")
    if len(geoms) != 1:
        raise RobotError(where, _tag(body), f"expected exactly one {kind} geom, found {len(geoms)}")
    g = defaults.resolve(geoms[0], _GEOM_DEFAULTS)
    if g["type"] != kind:
        raise RobotError(where, _tag(geoms[0]), f'type "{g["type"]}" is not allowed; expected "{kind}"')
    return geoms[0], g


def _read_limb(where: str, body: ET.Element, parent: int, defaults: _Defaults, degrees: bool) -> Limb:
    m = _LIMB_RE.match(body.get("name", ""))
    if not m:
        raise RobotError(where, _tag(body), 'expected a limb body named "limb/<integer>"')
    lid = int(m.group(1))
    _check_no_rotation(where, body)
    pos = _floats(where, body, "pos", 3, body.get("pos", "0 0 0"))
    for el in body:
        if el.tag in ("freejoint", "inertial", "composite", "flexcomp"):
            raise RobotError(where, _tag(el), f"<{el.tag}> is not allowed in a UNIMAL limb")
    geom, g = _one_geom(where, body, "capsule", defaults)
    if g.get("fromto") is None:
        raise RobotError(where, _tag(geom), 'attribute "fromto" is missing; expected "0 0 0 x y z"')
    ft = _floats(where, geom, "fromto", 6, g["fromto"])
    if any(abs(v) > 1e-9 for v in ft[:3]):
        raise RobotError(where, _tag(geom), f'fromto="{g["fromto"]}": a UNIMAL capsule starts at the body origin (0 0 0)')
    if np.linalg.norm(ft[3:]) < 1e-6:
        raise RobotError(where, _tag(geom), f'fromto="{g["fromto"]}": zero-length capsule')
    radius = _floats(where, geom, "size", (1, 2, 3), g.get("size"))[0]
    if radius <= 0:
        raise RobotError(where, _tag(geom), f'size="{g.get("size")}": expected a positive radius')
    density = _positive(where, geom, "density", g["density"])

    joints: list[Joint] = []
    for el in body.findall("joint"):
        a = defaults.resolve(el, _MUJOCO_JOINT_DEFAULTS)
        if a["type"] != "hinge":
            raise RobotError(where, _tag(el), f'type "{a["type"]}" is not allowed; UNIMAL limbs have hinge joints only')
        jm = _JOINT_RE.match(el.get("name", ""))
        if not jm or int(jm.group(2)) != lid:
            raise RobotError(where, _tag(el), f'expected a hinge named "limbx/{lid}" or "limby/{lid}"')
        if a.get("range") is None:
            raise RobotError(where, _tag(el), 'attribute "range" is missing')
        lo, hi = _floats(where, el, "range", 2, a["range"])
        if not degrees:
            lo, hi = math.degrees(lo), math.degrees(hi)
        if not lo < hi:
            raise RobotError(where, _tag(el), f'range="{a["range"]}": expected lo < hi')
        if a.get("limited", "auto") == "false":
            raise RobotError(where, _tag(el), 'limited="false": UNIMAL limb joints are limited')
        axis = _floats(where, el, "axis", 3, a.get("axis", "0 0 1"))
        if np.linalg.norm(axis) < 1e-6:
            raise RobotError(where, _tag(el), f'axis="{a.get("axis")}": zero axis')
        joints.append(Joint(kind=jm.group(1), pos=_floats(where, el, "pos", 3, a.get("pos", "0 0 0")), axis=axis,
                            range=(lo, hi), gear=0.0,
                            armature=_floats(where, el, "armature", 1, a["armature"])[0],
                            damping=_floats(where, el, "damping", 1, a["damping"])[0],
                            stiffness=_floats(where, el, "stiffness", 1, a["stiffness"])[0]))
    if not joints:
        raise RobotError(where, _tag(body), "a UNIMAL limb has 1 or 2 hinge joints, found none")
    if len(joints) > MAX_JOINTS_PER_LIMB:
        raise RobotError(where, _tag(body), f"{len(joints)} joints; a UNIMAL limb has at most {MAX_JOINTS_PER_LIMB}")
    if [j.kind for j in joints] not in (["x"], ["y"], ["x", "y"]):
        raise RobotError(where, _tag(body), f"joints {[f'limb{j.kind}/{lid}' for j in joints]}: expected limbx before limby, each at most once")
    return Limb(id=lid, parent=parent, pos=pos, tip=ft[3:], joints=tuple(joints), radius=float(radius), density=density)


def _read_motors(where: str, root: ET.Element, limbs: list[Limb]) -> list[Limb]:
    """Attach each motor's gear to its joint; every joint needs exactly one motor, and nothing else may act."""
    names = {f"limb{j.kind}/{l.id}": (i, j.kind) for i, l in enumerate(limbs) for j in l.joints}
    gears: dict[str, float] = {}
    act = root.find("actuator")
    for el in (act if act is not None else []):
        if el.tag != "motor":
            raise RobotError(where, _tag(el), f"<{el.tag}> is not allowed; UNIMAL robots are driven by <motor> only")
        joint = el.get("joint")
        if joint not in names:
            raise RobotError(where, _tag(el), f'joint="{joint}" is not a limb joint of this robot')
        if joint in gears:
            raise RobotError(where, _tag(el), f'a second motor on joint "{joint}"')
        gear = _floats(where, el, "gear", (1, 6), el.get("gear", "1"))
        if any(abs(g) > 0 for g in gear[1:]):
            raise RobotError(where, _tag(el), f'gear="{el.get("gear")}": only the first gear component may be set')
        gears[joint] = gear[0]
    missing = [n for n in names if n not in gears]
    if missing:
        raise RobotError(where, "<actuator>", f"missing motor for joint(s) {', '.join(missing)}")
    out = []
    for l in limbs:
        js = tuple(Joint(**{**j.__dict__, "gear": gears[f"limb{j.kind}/{l.id}"]}) for j in l.joints)
        out.append(Limb(**{**l.__dict__, "joints": js}))
    return out


def robot_files(folder: str | Path) -> list[Path]:
    """The robot XML files of a MetaMorph folder (`xml/*.xml`), or of a plain folder of XML files, sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RobotError(str(folder), "", "no such folder")
    xml_dir = folder / "xml" if (folder / "xml").is_dir() else folder
    files = sorted(xml_dir.glob("*.xml"))
    if not files:
        raise RobotError(str(folder), "", "no robot files (expected xml/<id>.xml and metadata/<id>.json)")
    return files


def load_folder(folder: str | Path, *, allow_outside_design_space: bool = False) -> list[Morphology]:
    """All robots of a folder in MetaMorph format, sorted by id. The first bad file raises (see `load_robot`)."""
    return [load_robot(f, allow_outside_design_space=allow_outside_design_space) for f in robot_files(folder)]
