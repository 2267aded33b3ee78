"""MJCF sources: files, XML strings, dm_control suite scenes, the suite tasks that build a scene of
their own, and KeyCLD's variants of them.

Every source resolves to one self-contained XML text (includes inlined), so that a recording can carry
the exact scene it came from. KeyCLD's scenes are made by editing dm_control's suite XML in code.
"""

import copy
import functools
import os
import pathlib
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable

import mujoco

from .._keycld import KEYCLD_SCENES
from .._misc import optional_import

_KEYCLD_PREFIX = "keycld/"

# suite tasks whose scene is not their domain's default: "<domain>/<task>" -> the domain and the
# arguments of its `get_model_and_assets` that the task passes
_SUITE_TASKS = {
    "cartpole/two_poles": ("cartpole", (("num_poles", 2),)),
    "cartpole/three_poles": ("cartpole", (("num_poles", 3),)),
}


def _import_quietly(name: str):
    """Import a dm_control module without the warning that no display is there for GLFW rendering."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", module="glfw")
        return optional_import(name, purpose="dm_control's suite scenes")


def _suite_domains() -> tuple[str, ...]:
    import pkgutil

    suite = _import_quietly("dm_control.suite")

    names = []
    for module in pkgutil.iter_modules(suite.__path__):
        if module.name in ("base", "common", "utils", "wrappers", "explore") or "test" in module.name:
            continue
        if module.name == "lqr_solver":
            continue
        names.append(module.name)
    return tuple(sorted(names))


def _inline_includes(root: ET.Element, read: Callable[[str], bytes], where: str) -> ET.Element:
    """Replace every `<include file=...>` by the children of the included file's `<mujoco>`."""
    for parent in list(root.iter()):
        for index, child in reversed(list(enumerate(list(parent)))):
            if child.tag != "include":
                continue
            name = child.get("file")
            if name is None:
                raise ValueError(f"{where}: an <include> element has no file attribute")
            try:
                text = read(name)
            except (KeyError, FileNotFoundError) as error:
                raise FileNotFoundError(f"{where}: included file {name!r} not found") from error
            included = _inline_includes(ET.fromstring(text), read, name)
            parent.remove(child)
            for offset, element in enumerate(list(included)):
                parent.insert(index + offset, element)
    return root


def _to_text(root: ET.Element) -> str:
    return ET.tostring(root, encoding="unicode")


@functools.cache
def _suite_root(name: str, arguments: tuple[tuple[str, int], ...] = ()) -> ET.Element:
    module = _import_quietly(f"dm_control.suite.{name}")
    try:
        xml, assets = module.get_model_and_assets(**dict(arguments))
    except (AttributeError, TypeError):  # domains that generate their MJCF from arguments in code
        raise ValueError(
            f"dm_control suite domain {name!r} builds its MJCF in code, not from a fixed XML file; give "
            "the MJCF as a file or an XML string instead"
        ) from None

    def read(file):
        return assets[file]

    return _inline_includes(ET.fromstring(xml), read, f"dm_control suite {name!r}")


def _find(root: ET.Element, path: str) -> ET.Element:
    element = root.find(path)
    if element is None:  # the suite changed under us: say where
        raise RuntimeError(f"dm_control's suite XML has no element {path!r}; cannot build the KeyCLD scene")
    return element


def _unlimit(actuator: ET.Element) -> None:
    actuator.attrib.pop("ctrlrange", None)
    actuator.set("ctrllimited", "false")


def _restyle(root: ET.Element, name: str, physics: bool, **look: str) -> None:
    """Give the geom `name` KeyCLD's `look` (size, material). With `physics`, the geom itself changes
    (its inertia with its size); without, the geom keeps its physics out of sight (geom group 3, which
    MuJoCo's renderers hide by default) and a massless twin with the look is what the camera sees."""
    geom = _find(root, f".//geom[@name='{name}']")
    if physics:
        for attribute, value in look.items():
            geom.set(attribute, value)
        return
    twin = copy.deepcopy(geom)
    twin.attrib.update(name=f"{name}_look", mass="0", contype="0", conaffinity="0", group="0", **look)
    twin.attrib.pop("density", None)
    geom.set("group", "3")
    parent = next(e for e in root.iter() if geom in list(e))
    parent.insert(list(parent).index(geom) + 1, twin)


def _keycld_pendulum(root: ET.Element, physics: bool) -> None:
    camera = _find(root, ".//camera[@name='fixed']")
    camera.set("pos", "0 -2.5 .6")
    camera.set("xyaxes", "1 0 0 0 0 1")
    if physics:
        _find(root, ".//joint[@name='hinge']").set("damping", "0")
        motor = _find(root, "./actuator/motor[@name='torque']")
        motor.set("gear", "2")
        _unlimit(motor)


def _keycld_cartpole(root: ET.Element, physics: bool) -> None:
    if physics:  # the pole's class sets its size
        _find(root, "./default/default[@class='pole']/geom").set("size", "0.09")
    else:
        _restyle(root, "pole_1", physics, size="0.09")
    _find(root, ".//camera[@name='fixed']").set("pos", "0 -6 1")
    for rail in ("rail1", "rail2"):
        _find(root, f".//geom[@name='{rail}']").set("size", "0.02 4")
    floor = _find(root, ".//geom[@name='floor']")
    floor.set("pos", "0 0 -.2")
    floor.set("size", "8 8 .2")
    _find(root, ".//geom[@name='cart']").set("material", "decoration")
    if physics:
        _find(root, "./default/default[@class='pole']/joint").set("damping", "0")
        slider = _find(root, ".//joint[@name='slider']")
        slider.set("damping", "0")
        slider.set("limited", "false")
        actuators = _find(root, "./actuator")
        slide = _find(actuators, "./motor[@name='slide']")
        slide.set("gear", "4")
        _unlimit(slide)
        ET.SubElement(actuators, "motor", name="hinge_1", joint="hinge_1", gear="1", ctrllimited="false")


def _keycld_acrobot(root: ET.Element, physics: bool) -> None:
    # the shoulder moves with the camera: a translation, which changes nothing in the dynamics
    _find(root, ".//camera[@name='fixed']").set("pos", "0 -6 2.1")
    _find(root, ".//body[@name='upper_arm']").set("pos", "0 0 2.1")
    _restyle(root, "upper_arm", physics, size="0.1", material="decoration")
    _restyle(root, "lower_arm", physics, size="0.098")
    if physics:
        _find(root, "./default/joint").set("damping", "0")
        actuators = _find(root, "./actuator")
        elbow = _find(actuators, "./motor[@name='elbow']")
        _unlimit(elbow)
        shoulder = ET.Element("motor", name="shoulder", joint="shoulder", gear="2", ctrllimited="false")
        actuators.insert(list(actuators).index(elbow), shoulder)


_EDITS = {"pendulum": _keycld_pendulum, "cartpole": _keycld_cartpole, "acrobot": _keycld_acrobot}
_PHYSICS = ("keycld", "stock")


def keycld_scene(name: str, *, physics: str = "keycld") -> str:
    """The MJCF of one of KeyCLD's scenes, made by editing dm_control's suite XML.

    The changes follow the KeyCLD paper (appendix A.6) and its authors' fork of dm_control: no joint
    damping, no cartpole rail limit, a motor on every joint (pendulum gear 2; cartpole slide gear 4
    and hinge gear 1; acrobot shoulder gear 2 and elbow gear 2), no control limits, and cameras and
    geometry moved so that the plane of motion faces the `fixed` camera (pendulum camera at
    `(0, -2.5, .6)`; cartpole camera at `(0, -6, 1)`, longer rails, floor at `z = -0.2`, pole radius
    0.09, cart coloured `decoration`; acrobot camera at `(0, -6, 2.1)`, shoulder at `z = 2.1`, both arm
    radii doubled, upper arm coloured `decoration`).

    With `physics="stock"` the scene keeps dm_control's own physics (its joint damping, rail limit,
    actuators, gears, control limits, and the masses and inertias of its geoms) and takes only
    KeyCLD's camera and look: a system a model trained on KeyCLD's frames can see, with effects
    nobody declared to it. A geom whose look changes its size stays as dm_control has it, hidden
    from the camera (geom group 3), beside a massless twin that shows KeyCLD's size and colour; the
    acrobot's shoulder moves up with the camera, which leaves its dynamics unchanged.

    The stock scenes stay available by their suite name (`"cartpole"`); the variants are also
    reachable as `"keycld/cartpole"` and `"keycld/cartpole:stock"` wherever an MJCF is accepted.

    **Arguments:**

    - `name`: `"pendulum"`, `"cartpole"` or `"acrobot"` (a `"keycld/"` prefix and a `":stock"` or
      `":keycld"` suffix are accepted).
    - `physics`: `"keycld"` (the paper's scenes) or `"stock"` (dm_control's physics, KeyCLD's camera
      and look).

    **Returns:** the self-contained XML text (includes inlined), loadable with
    `mujoco.MjModel.from_xml_string` or `dm_control.mujoco.Physics.from_xml_string`.

    !!! example

        ```python
        xml = cldyn.mujoco.keycld_scene("acrobot")
        physics = dm_control.mujoco.Physics.from_xml_string(xml)
        stock = cldyn.mujoco.keycld_scene("acrobot", physics="stock")  # damping 0.05, elbow motor
        ```
    """
    key = name.removeprefix(_KEYCLD_PREFIX)
    if ":" in key:
        key, physics = key.split(":", 1)
    if key not in _EDITS:
        raise ValueError(f"unknown KeyCLD scene {name!r}; choose one of {', '.join(KEYCLD_SCENES)}")
    if physics not in _PHYSICS:
        raise ValueError(f"physics must be one of {', '.join(_PHYSICS)}, got {physics!r}")
    root = copy.deepcopy(_suite_root(key))
    stock = physics == "stock"
    root.set("model", f"keycld-{'stock-' if stock else ''}{root.get('model', key)}")
    _EDITS[key](root, not stock)
    return _to_text(root)


def _looks_like_xml(text: str) -> bool:
    return text.lstrip().startswith("<")


def _is_path_like(text: str) -> bool:
    return text.endswith((".xml", ".mjcf")) or os.sep in text or "/" in text


def scene_xml(mjcf: "str | os.PathLike") -> str:
    """The self-contained MJCF text of a scene, with `<include>` elements inlined.

    **Arguments:**

    - `mjcf`: a path to an MJCF file, an XML string, the name of a dm_control suite domain
      (`"acrobot"`, `"cartpole"`, ...), `"<domain>/<task>"` for a suite task that builds a scene of
      its own (`"cartpole/two_poles"`, `"cartpole/three_poles"`: the stock cart-pole with a chain of
      two or three poles), or `"keycld/<name>"` for KeyCLD's variants (see `keycld_scene`).

    **Returns:** the XML text. Files the model references (meshes, textures) stay references.
    """
    if isinstance(mjcf, os.PathLike):
        return _file_text(pathlib.Path(mjcf))
    if not isinstance(mjcf, str):
        raise TypeError(f"mjcf must be a path, an XML string or a scene name, got {type(mjcf).__name__}")
    if _looks_like_xml(mjcf):
        try:  # a clear parse error now rather than a MuJoCo one later
            ET.fromstring(mjcf)
        except ET.ParseError as error:
            raise ValueError(f"the MJCF string is not well-formed XML: {error}") from None
        return mjcf
    if os.path.isfile(mjcf):
        return _file_text(pathlib.Path(mjcf))
    if mjcf.startswith(_KEYCLD_PREFIX):
        return keycld_scene(mjcf)
    if mjcf in _SUITE_TASKS:
        domain, arguments = _SUITE_TASKS[mjcf]
        root = copy.deepcopy(_suite_root(domain, arguments))
        root.set("model", f"{root.get('model', domain)}-{mjcf.split('/')[1].replace('_', '-')}")
        return _to_text(root)
    if not _is_path_like(mjcf):
        domains = _suite_domains()
        if mjcf in domains:
            return _to_text(copy.deepcopy(_suite_root(mjcf)))
        raise ValueError(
            f"unknown scene {mjcf!r}: not a file, not XML, not a dm_control suite domain "
            f"({', '.join(domains)}), not a suite task with a scene of its own ({', '.join(_SUITE_TASKS)}) "
            f"and not keycld/<{'|'.join(KEYCLD_SCENES)}>"
        )
    raise FileNotFoundError(f"MJCF file not found: {mjcf}")


def _file_text(path: pathlib.Path) -> str:
    if not path.is_file():
        raise FileNotFoundError(f"MJCF file not found: {path}")
    directory = path.parent

    def read(file):
        return (directory / file).read_bytes()

    try:
        root = ET.fromstring(path.read_bytes())
    except ET.ParseError as error:
        raise ValueError(f"{path}: not valid XML ({error})") from error
    return _to_text(_inline_includes(root, read, str(path)))


def load_model(mjcf: "str | os.PathLike") -> tuple[mujoco.MjModel, str, str]:
    """Compile a scene: `(model, xml_text, source)`, where `source` names where it came from."""
    if isinstance(mjcf, os.PathLike) or (
        isinstance(mjcf, str) and not _looks_like_xml(mjcf) and os.path.isfile(mjcf)
    ):
        path = pathlib.Path(mjcf)
        text = scene_xml(path)
        try:
            model = mujoco.MjModel.from_xml_path(str(path))
        except ValueError as error:
            raise ValueError(f"{path}: MuJoCo could not compile it: {error}") from error
        return model, text, str(path)
    text = scene_xml(mjcf)
    try:
        model = mujoco.MjModel.from_xml_string(text)
    except ValueError as error:
        raise ValueError(f"MuJoCo could not compile the MJCF: {error}") from error
    source = "<xml string>" if _looks_like_xml(mjcf) else mjcf
    return model, text, source
