"""Identification against MuJoCo: recordings in, reports out; and scenes with injected effects."""

import argparse
import os
import pathlib
import xml.etree.ElementTree as ET
from collections.abc import Mapping

import jax

from .._identify import EFFECTS, Criteria, Identification, Smoothing, identify
from ._bridge import from_mjcf
from ._record import Recording
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
    data: "Recording | str | os.PathLike",
    nominal: "str | os.PathLike",
    **kwargs,
) -> Identification:
    """`cldyn.identify` for data recorded from MuJoCo, against the `from_mjcf` model of a nominal MJCF.

    The nominal model is built from `nominal` with the recording's keypoints (by name), so the
    recording and the model agree on what each coordinate is; joint effects are named by the MJCF's
    joints, gain errors by its actuators, keypoint effects by the keypoints. Runs in float64.

    **Arguments:**

    - `data`: a `Recording`, or the path of one saved by `cldyn record`.
    - `nominal`: the nominal MJCF (path, XML string, suite name or `"keycld/<name>"`): the model
      without the effect to be found.
    - `kwargs`: passed on to `cldyn.identify` (`effects`, `smoothing`, `criteria`, `bootstrap`, ...).

    **Returns:** an `Identification`; `.save(dir)` writes `report.json`, `report.md` and plots.
    """
    jax.config.update("jax_enable_x64", True)
    if not isinstance(data, Recording):
        data = Recording.load(data)
    bridge = from_mjcf(nominal)
    if bridge.keypoint_names != data.keypoint_names:
        try:
            bridge = from_mjcf(nominal, keypoints=data.keypoint_names)
        except ValueError as error:
            raise ValueError(
                f"the recording's keypoints {list(data.keypoint_names)} are not keypoints of the nominal "
                f"model (its defaults are {list(bridge.keypoint_names)}): {error}"
            ) from error
    if bridge.joint_names != data.joint_names:
        raise ValueError(
            f"the recording's joints {list(data.joint_names)} differ from the nominal model's "
            f"{list(bridge.joint_names)}"
        )
    if bridge.actuator_names != data.actuator_names:
        raise ValueError(
            f"the recording's actuators {list(data.actuator_names)} differ from the nominal model's "
            f"{list(bridge.actuator_names)}"
        )
    result = identify(
        bridge.system,
        data.x,
        data.u,
        data.dt,
        joint_coordinates=dict(zip(bridge.joint_names, bridge.joint_coordinates)),
        joints=bridge.joints,
        actuator_names=bridge.actuator_names,
        keypoint_names=bridge.keypoint_names,
        **kwargs,
    )
    result.settings.update(
        data=str(data.mjcf),
        nominal=str(nominal) if not str(nominal).lstrip().startswith("<") else "<xml>",
        noise=data.noise,
        record_seed=data.seed,
    )
    return result


# -- command line -------------------------------------------------------------------------------


def _identify_command(args: argparse.Namespace) -> int:
    smoothing = Smoothing(
        window=args.window, order=args.order, test_width=args.test_width, test_stride=args.test_stride
    )
    result = identify_recording(
        args.data,
        args.model,
        effects=tuple(args.effects),
        smoothing=smoothing,
        criteria=Criteria(),
        bootstrap=args.bootstrap,
        holdout=args.holdout,
        max_rounds=args.max_rounds,
        seed=args.seed,
        progress=True,
    )
    out = result.save(args.out)
    print(result.summary())
    print(f"wrote {out / 'report.json'}, {out / 'report.md'} and plots")
    return 0


def register(subparsers) -> None:
    """Add `cldyn identify`."""
    parser = subparsers.add_parser(
        "identify",
        help="find the physics a nominal MJCF model is missing in recorded data",
        description=(
            "Compute the residual of the nominal model on recorded data, attribute it to effects of the "
            "library (damping, Coulomb friction, springs, armature, actuator gain, drag, point masses), "
            "add them, refit, and report the error before and after."
        ),
    )
    parser.add_argument("--data", required=True, help="a recording saved by `cldyn record` (.npz)")
    parser.add_argument("--model", required=True, help="the nominal MJCF (file, suite name or keycld/<name>)")
    parser.add_argument(
        "--out", required=True, type=pathlib.Path, help="directory for report.json/md and plots"
    )
    parser.add_argument(
        "--effects", nargs="+", default=list(EFFECTS), choices=EFFECTS, help="effects to consider"
    )
    parser.add_argument("--bootstrap", type=int, default=100, help="bootstrap replicates (default 100)")
    parser.add_argument(
        "--holdout", type=float, default=0.25, help="fraction of runs held out (default 0.25)"
    )
    parser.add_argument("--max-rounds", type=int, default=3, help="detect-augment-refit rounds (default 3)")
    parser.add_argument(
        "--window", type=int, default=Smoothing.window, help="Savitzky-Golay window (samples)"
    )
    parser.add_argument("--order", type=int, default=Smoothing.order, help="Savitzky-Golay polynomial order")
    parser.add_argument("--test-width", type=int, default=Smoothing.test_width, help="test function width")
    parser.add_argument("--test-stride", type=int, default=Smoothing.test_stride, help="test function stride")
    parser.add_argument("--seed", type=int, default=0, help="seed of the split and the bootstrap")
    parser.set_defaults(run=_identify_command)
