"""How finely an estimator reads a small turn near the target, through MuJoCo's render and through a
camera whose pixels integrate light over their area (`keyvision.RenderProtocol(supersample=)`).

Energy shaping from frames holds the acrobot upright only if the estimator's reading of a turn of a
degree or two near upright follows the turn: a reading that changes by a factor `gamma` of the true
change lowers the loop's stiffness to `kp gamma - rate (1 - gamma)` (`docs/acrobot_from_frames.md`).
For each model: the scene is posed at upright and each hinge turned alone from -20 to 20 degrees in
steps of 0.5 degrees (`keyvision.render_poses`), the frames are encoded by the model's estimator and
the hinge angle is read from its keypoints (`keyvision.joint_structure`). Reported per camera and
hinge: the local gain (the reading's change over the turn's, step by step) mean and standard
deviation, the secant gains over +-1 and +-2 degrees, and the reading's RMS residual from a straight
line (degrees). Cameras: MuJoCo's render (`supersample=1`, the paper's frames: 4 samples per pixel,
so a link one or two pixels wide moves the frame in quarter-coverage steps) and 4 x 4 samples per
pixel averaged (`supersample=4`).

Writes benchmarks/results/vision_camera.{json,md} and vision_camera.png (each reading against the
turn); prints the JSON.

    python benchmarks/vision_camera.py --model acrobot=benchmarks/results/vision_models/acrobot-augmented
"""

import argparse
import os
import pathlib
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, repo_path, write  # noqa: E402

TURN_DEGREES = np.arange(-20.0, 20.001, 0.5)
CAMERAS = (1, 4)


def _upright(scene: str, size: int) -> tuple[np.ndarray, list[str], list[int]]:
    """The scene's upright posture (`qpos`), its hinges' names and `qpos` addresses, as
    `keyvision.swing_up` finds the posture."""
    import mujoco

    from keyvision import RenderProtocol
    from keyvision._control import _postures
    from keyvision._data import PlanarCamera
    from keyvision._render import _scene_xml
    from keyvision._scene import _HINGE, _scene

    setup = _scene(_scene_xml(scene), RenderProtocol(image_size=size), "fixed", None)
    data = mujoco.MjData(setup.model)
    _, upright = _postures(mujoco, setup, data, PlanarCamera(setup.homography, setup.basis))
    physics = setup.model
    hinges = [j for j in range(physics.njnt) if physics.jnt_type[j] == _HINGE]
    names = [mujoco.mj_id2name(physics, mujoco.mjtObj.mjOBJ_JOINT, j) for j in hinges]
    return upright, names, [int(physics.jnt_qposadr[j]) for j in hinges]


def _readings(model, scene: str, supersample: int) -> dict:
    import jax.numpy as jnp

    import keyvision
    from keyvision._evaluate import encode_batch

    upright, names, addresses = _upright(scene, model.image_size)
    base = keyvision.render_poses(scene, upright[None], image_size=model.image_size, supersample=supersample)
    x_up = np.asarray(encode_batch(model, base["frames"]), np.float64)
    structure = keyvision.joint_structure(model.dynamics.constraint, x_up, names=names)
    turns = np.deg2rad(TURN_DEGREES)
    out = {}
    for name, address in zip(names, addresses):
        qpos = np.tile(upright, (len(turns), 1))
        qpos[:, address] += turns
        frames = keyvision.render_poses(scene, qpos, image_size=model.image_size, supersample=supersample)
        x = jnp.asarray(np.asarray(encode_batch(model, frames["frames"]), np.float64))
        read = np.unwrap(np.asarray([float(structure.coordinates[name](xi)) for xi in x]))
        read = np.sign(np.polyfit(turns, read, 1)[0]) * (read - read[len(turns) // 2])  # the turn's sense
        gain = np.diff(read) / np.diff(turns)
        line = np.polyfit(turns, read, 1)
        middle = len(turns) // 2
        secant = {}
        for degrees in (1, 2):
            low, high = middle - 2 * degrees, middle + 2 * degrees  # steps of 0.5 degrees
            secant[degrees] = float((read[high] - read[low]) / (turns[high] - turns[low]))
        out[name] = {
            "reading_degrees": np.rad2deg(read).round(4).tolist(),
            "local_gain_mean": float(gain.mean()),
            "local_gain_std": float(gain.std()),
            "secant_gain_1deg": secant[1],
            "secant_gain_2deg": secant[2],
            "slope": float(line[0]),
            "residual_rms_degrees": float(np.rad2deg(np.std(read - np.polyval(line, turns)))),
        }
    return out


def _plot(path, results) -> None:
    import matplotlib.pyplot as plt

    rows = [(name, joint) for name in results for joint in results[name]["cameras"]["1"]]
    figure, axes = plt.subplots(1, len(rows), figsize=(4.6 * len(rows), 3.6), layout="constrained")
    for axis, (name, joint) in zip(np.atleast_1d(axes), rows):
        for camera, reading in results[name]["cameras"].items():
            values = np.asarray(reading[joint]["reading_degrees"]) - TURN_DEGREES
            label = "MuJoCo's render" if camera == "1" else f"{camera} x {camera} samples per pixel"
            axis.plot(TURN_DEGREES, values, marker=".", markersize=3, linewidth=0.8, label=label)
        axis.axhline(0.0, color="k", linewidth=0.6)
        axis.set(xlabel=f"{joint} turned from upright (deg)", ylabel="reading minus turn (deg)", title=name)
        axis.legend(fontsize=8)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append", required=True, metavar="SCENE=DIR")
    args = parser.parse_args()
    import keyvision
    from keyvision._files import trained_supersample

    results = {}
    for item in args.model:
        scene, directory = item.split("=", 1)
        model, spec = keyvision.load_model(directory)
        name = pathlib.Path(directory).name
        trained = trained_supersample(spec)
        results[name] = {
            "scene": f"keycld/{scene}",
            "model": repo_path(directory),
            "trained_on_supersample": trained,
            "cameras": {str(c): _readings(model, f"keycld/{scene}", c) for c in CAMERAS},
        }
        spread = {
            c: {j: round(v["local_gain_std"], 3) for j, v in r.items()}
            for c, r in results[name]["cameras"].items()
        }
        print(name, "local gain std by camera:", spread, flush=True)
    lines = [
        "# How finely an estimator reads a small turn near upright, by camera",
        "",
        "Each hinge turned alone from upright, -20 to 20 degrees in steps of 0.5, the others upright; the "
        "angle read from the model's keypoints. Local gain: the reading's change over the turn's, step by "
        "step (mean, standard deviation); secant: over +-1 and +-2 degrees; residual: RMS from a straight "
        "line. Camera 1: MuJoCo's render (the paper's frames); 4: each pixel the mean of 4 x 4 samples. "
        "Written by `benchmarks/vision_camera.py`.",
        "",
        "| model | trained on camera | camera | hinge | local gain mean | local gain std | secant +-1 deg | "
        "secant +-2 deg | residual (deg) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, result in results.items():
        for camera, readings in result["cameras"].items():
            for joint, r in readings.items():
                lines.append(
                    f"| {name} | {result['trained_on_supersample']} | {camera} | {joint} | "
                    f"{r['local_gain_mean']:.3f} | {r['local_gain_std']:.3f} | {r['secant_gain_1deg']:.3f} | "
                    f"{r['secant_gain_2deg']:.3f} | {r['residual_rms_degrees']:.3f} |"
                )
    _plot(RESULTS / "vision_camera.png", results)
    result = {"machine": machine(), "turn_degrees": TURN_DEGREES.tolist(), "models": results}
    write("vision_camera", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
