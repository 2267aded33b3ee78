"""The frames' controls as a model's inputs: placed by the name of the actuator behind each input."""

import dataclasses

import numpy as np


def scene_actuators(scene: str) -> tuple[str, ...]:
    """The names of a scene's actuators, in MuJoCo's order: the `inputs` of `identify` for a model
    trained on frames of `scene` (what `keyvision.render` accepts: `"keycld/acrobot"`, an MJCF)."""
    from ._render import _scene_xml
    from ._scene import _mujoco

    mujoco = _mujoco()
    model = mujoco.MjModel.from_xml_string(_scene_xml(scene))
    return tuple(
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or f"actuator{a}" for a in range(model.nu)
    )


def _place_controls(frames, inputs, num_inputs: int):
    """The frames with their controls laid out as the model's inputs (see `identify`'s `inputs`)."""
    count = frames.u.shape[-1]
    if inputs is None:
        if count != num_inputs:
            raise ValueError(
                f"identify: the frames have {count} controls and the model {num_inputs} inputs; name the "
                "actuator of each input with inputs= to place the frames' controls by name"
            )
        return frames
    inputs = tuple(str(name) for name in inputs)
    if len(inputs) != num_inputs:
        raise ValueError(f"identify: inputs names {len(inputs)} actuators; the model has {num_inputs} inputs")
    names = [str(name) for name in frames.info.get("actuator_names", [])]
    if len(names) != count:
        raise ValueError(
            f"identify: the frames name {len(names)} actuators for their {count} controls "
            "(frames.info['actuator_names']): cannot place them by name"
        )
    u = np.zeros((*frames.u.shape[:-1], num_inputs), dtype=frames.u.dtype)
    for column, name in enumerate(names):
        if name not in inputs:
            raise ValueError(
                f"identify: the frames' actuator {name!r} drives none of the model's inputs {inputs}"
            )
        u[..., inputs.index(name)] = frames.u[..., column]
    return dataclasses.replace(frames, u=u)
