"""Identification against MuJoCo: recordings in, reports out; and scenes with injected effects."""

import dataclasses
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping

from .._data import Sequences
from .._identify import Identification, identify
from ._bridge import from_mjcf
from ._scenes import scene_xml

_JOINT_ATTRIBUTES = ("damping", "frictionloss", "stiffness", "springref", "armature")
_ACTUATOR_ATTRIBUTES = ("gear",)


def modify_scene(
    mjcf: "str | os.PathLike",
    *,
    joints: Mapping[str, Mapping[str, float]] | None = None,
    actuators: Mapping[str, Mapping[str, float]] | None = None,
    flags: Mapping[str, str] | None = None,
) -> str:
    """A scene with attributes of named joints and actuators set: how to inject an effect.

    **Arguments:**

    - `mjcf`: a path, an XML string, a dm_control suite name or `"keycld/<name>"`.
    - `joints`: joint name -> `{attribute: value}` for `damping`, `frictionloss`, `stiffness`,
      `springref` and `armature`, in the MJCF's own units (`springref` of a hinge is in the compiler's
      angle unit: degrees for dm_control's scenes, as MuJoCo's default).
    - `actuators`: actuator name -> `{"gear": value}`.
    - `flags`: MuJoCo `<option><flag>` settings, e.g. `{"constraint": "enable"}`: frictionloss is a
      constraint in MuJoCo and acts only where constraints are enabled (dm_control's acrobot disables
      them).

    **Returns:** the modified XML text.

    !!! example

        ```python
        xml = cldyn.mujoco.modify_scene("keycld/pendulum", joints={"hinge": {"damping": 0.1}})
        data = cldyn.mujoco.record(xml, runs=40, duration=4.0, dt=0.01)
        ```
    """
    root = ET.fromstring(scene_xml(mjcf))
    for kind, changes, allowed in (
        ("joint", joints or {}, _JOINT_ATTRIBUTES),
        ("actuator", actuators or {}, _ACTUATOR_ATTRIBUTES),
    ):
        for name, attributes in changes.items():
            if kind == "joint":
                elements = [e for e in root.iter("joint") if e.get("name") == name]
            else:
                section = root.find("actuator")
                elements = [e for e in (section if section is not None else []) if e.get("name") == name]
            if not elements:
                raise ValueError(f"the scene has no {kind} named {name!r}")
            for attribute, value in attributes.items():
                if attribute not in allowed:
                    raise ValueError(f"cannot set {kind} attribute {attribute!r}; allowed: {list(allowed)}")
                elements[0].set(attribute, repr(float(value)) if attribute != "gear" else _gear(value))
    if flags:
        option = root.find("option")
        if option is None:
            option = ET.SubElement(root, "option")
        flag = option.find("flag")
        if flag is None:
            flag = ET.SubElement(option, "flag")
        for name, value in flags.items():
            if value not in ("enable", "disable"):
                raise ValueError(f"flag {name!r} must be 'enable' or 'disable', got {value!r}")
            flag.set(name, value)
    return ET.tostring(root, encoding="unicode")


def _gear(value) -> str:
    return " ".join([repr(float(value))] + ["0"] * 5)


def identify_recording(
    data: "Sequences | str | os.PathLike",
    nominal: "str | os.PathLike",
    **kwargs,
) -> Identification:
    """`cldyn.identify` for data recorded from MuJoCo, against the `from_mjcf` model of a nominal MJCF.

    The nominal model is built from `nominal` with the recording's keypoints (by name), so the
    recording and the model agree on what each coordinate is; joint effects are named by the MJCF's
    joints, gain errors by its actuators, keypoint effects by the keypoints (the names come from
    `data.info`). The joint limits of the nominal MJCF (`bridge.joint_limits`), which the cldyn model
    does not express, are passed on: samples at a limit are left out. Runs in the precision JAX is
    set to: turn on JAX's 64-bit mode first, as the
    command line does (in float32 the result carries a warning).

    **Arguments:**

    - `data`: a `cldyn.Sequences` as `cldyn.mujoco.record` returns it, or the path of one saved by
      `cldyn record`.
    - `nominal`: the nominal MJCF (path, XML string, suite name or `"keycld/<name>"`): the model
      without the effect to be found.
    - `kwargs`: passed on to `cldyn.identify` (`effects`, `smoothing`, `criteria`, `bootstrap`,
      `progress_meter`, ...).

    **Returns:** an `Identification`; `.save(dir)` writes `report.json`, `report.md` and plots.

    !!! example

        ```python
        scene = cldyn.mujoco.modify_scene("keycld/pendulum", joints={"hinge": {"damping": 0.1}})
        data = cldyn.mujoco.record(scene, runs=20, duration=3.0, dt=0.01)
        result = cldyn.mujoco.identify_recording(data, "keycld/pendulum")
        ```
    """
    if not isinstance(data, Sequences):
        data = Sequences.load(data)
    info = data.info
    missing = [key for key in ("keypoint_names", "joint_names", "actuator_names") if key not in info]
    if missing:
        raise ValueError(f"the data's info lacks {missing}: record it with cldyn.mujoco.record")
    keypoint_names = tuple(info["keypoint_names"])
    bridge = from_mjcf(nominal)
    if bridge.keypoint_names != keypoint_names:
        try:
            bridge = from_mjcf(nominal, keypoints=keypoint_names)
        except ValueError as error:
            raise ValueError(
                f"the recording's keypoints {list(keypoint_names)} are not keypoints of the nominal "
                f"model (its defaults are {list(bridge.keypoint_names)}): {error}"
            ) from error
    for kind in ("joint", "actuator"):
        recorded, nominal_names = tuple(info[f"{kind}_names"]), getattr(bridge, f"{kind}_names")
        if recorded != tuple(nominal_names):
            raise ValueError(
                f"the recording's {kind}s {list(recorded)} differ from the nominal model's "
                f"{list(nominal_names)}"
            )
    kwargs.setdefault("joint_limits", bridge.limits())
    result = identify(
        bridge.system,
        data,
        joint_coordinates=dict(zip(bridge.joint_names, bridge.joint_coordinates)),
        joints=bridge.joints,
        actuator_names=bridge.actuator_names,
        keypoint_names=bridge.keypoint_names,
        **kwargs,
    )
    settings = dict(
        result.settings,
        data=str(info.get("mjcf")),
        nominal=str(nominal) if not str(nominal).lstrip().startswith("<") else "<xml>",
        noise=info.get("noise"),
        record_seed=info.get("seed"),
    )
    return dataclasses.replace(result, settings=settings)
