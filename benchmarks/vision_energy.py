"""What a KeyCLD model learnt from images knows about energy: its potential along posed sequences
(the paper's figures 8-12) and its energy along 500-frame predictions.

1. Potential. Each scene is rendered (`keyvision.render_poses`) along sequences of poses chosen by
   hand, as in the paper: the pendulum through a full rotation; the cart-pole's pole through a full
   rotation with the cart fixed, and the cart along its rail with the pole fixed; the acrobot's first
   link through a full rotation with the elbow straight, and its second link alone with the first
   hanging. The frames are encoded by the model's estimator and its learnt potential `V(x)` is set
   beside MuJoCo's potential energy of the same poses: a learnt potential is known up to a scale and
   an offset (the energy's unit follows the actions' unknown gains), so these are fitted by least
   squares and the correlation is reported. Where the true potential does not change (the cart moved
   with the pole fixed) the learnt one should not either: its spread is reported as a fraction of its
   spread along the other sequence of the scene.
2. Long horizon. From the first frames of new runs without control, each model predicts 500 frames
   (RK4 and projection, as `keyvision evaluate`); the learnt energy `T + V` along the prediction
   should stay constant. Reported: its drift over the 500 frames as a fraction of the learnt
   potential's swing along the same prediction, and the trend (a linear fit's change over the run,
   same unit).

Writes benchmarks/results/vision_energy.{json,md}, vision_potential_<scene>.png and
vision_long_<scene>.png (the energy over time, and every 50th predicted frame); prints the JSON.

    python benchmarks/vision_energy.py       # the shipped pendulum and the models of vision_models/
"""

import argparse
import os
import pathlib
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, VISION_MODELS, machine, write  # noqa: E402

MODELS = VISION_MODELS
TURN = np.linspace(0.0, 2 * np.pi, 73)  # every 5 degrees
RAIL = np.linspace(-1.0, 1.0, 41)  # the training runs start with the cart in U(-1, 1)
# scene -> [(sequence, parameter values, qpos along it)]; MuJoCo's hinge angle 0 is upright
SEQUENCES = {
    "pendulum": [("full rotation", TURN, TURN[:, None])],
    "cartpole": [
        ("pole rotation, cart fixed", TURN, np.stack([np.zeros_like(TURN), TURN], -1)),
        ("cart translation, pole hanging", RAIL, np.stack([RAIL, np.full_like(RAIL, np.pi)], -1)),
    ],
    "acrobot": [
        ("first link rotation, elbow straight", TURN, np.stack([TURN, np.zeros_like(TURN)], -1)),
        ("second link rotation, first hanging", TURN, np.stack([np.full_like(TURN, np.pi), TURN], -1)),
    ],
}
FLAT = 1e-9  # joules: a true potential that varies less than this along a sequence is constant
HORIZON = 500  # frames predicted
LONG_RUNS = 16  # runs predicted over the horizon
STRIP_EVERY = 50  # frames between those shown in the long prediction's strip


def _learnt_potential(model, frames: np.ndarray) -> np.ndarray:
    import equinox as eqx
    import jax

    images = frames.astype(np.float32) / 255
    x = eqx.filter_jit(lambda m, z: jax.vmap(m.encode)(z))(model, images)
    energy = eqx.filter_jit(lambda m, y: jax.vmap(m.dynamics.potential_energy)(y))(model, x)
    return np.asarray(energy, dtype=float)


def potential(scene: str, model, supersample: int = 1) -> list[dict]:
    import keyvision

    rows = []
    for name, parameter, qpos in SEQUENCES[scene]:
        poses = keyvision.render_poses(
            f"keycld/{scene}", qpos, image_size=model.image_size, supersample=supersample
        )
        learnt, true = _learnt_potential(model, poses["frames"]), poses["potential"]
        row = {
            "sequence": name,
            "parameter": parameter.tolist(),
            "true": true.tolist(),
            "learnt": learnt.tolist(),
            "true_range": float(np.ptp(true)),
            "learnt_range": float(np.ptp(learnt)),
        }
        if np.ptp(true) > FLAT:
            scale, offset = np.linalg.lstsq(np.stack([learnt, np.ones_like(learnt)], -1), true, rcond=None)[0]
            row.update(
                correlation=float(np.corrcoef(learnt, true)[0, 1]), scale=float(scale), offset=float(offset)
            )
        rows.append(row)
    changing = [row for row in rows if "correlation" in row]
    for row in rows:
        if "correlation" not in row and changing:
            # the learnt potential should be flat too: its spread against its spread where it must change
            row["flat_fraction"] = row["learnt_range"] / changing[0]["learnt_range"]
            row["scale"] = changing[0]["scale"]  # joules per learnt unit, from the sequence where it changes
    return rows


def _plot_potential(path: pathlib.Path, scene: str, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(
        1, len(rows), figsize=(4.2 * len(rows), 3.2), constrained_layout=True, squeeze=False
    )
    for axis, row in zip(axes[0], rows):
        parameter, true, learnt = (np.asarray(row[k]) for k in ("parameter", "true", "learnt"))
        unit = "rad" if "rotation" in row["sequence"] else "m"
        axis.plot(parameter, true, "k-", label="MuJoCo")
        if "correlation" in row:
            axis.plot(
                parameter,
                row["scale"] * learnt + row["offset"],
                "C1--",
                label=f"learnt, scaled (r = {row['correlation']:.3f})",
            )
        else:
            axis.plot(
                parameter,
                row["scale"] * (learnt - learnt.mean()) + true.mean(),
                "C1--",
                label=f"learnt, scaled, centred (spread {row['flat_fraction']:.1%})",
            )
        axis.set(xlabel=f"{row['sequence']} ({unit})", ylabel="potential energy (J)", title=scene)
        axis.legend(fontsize=8)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def long_horizon(scene: str, model, supersample: int = 1) -> tuple[dict, np.ndarray, np.ndarray]:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import cldyn
    import keyvision

    protocol = keyvision.RenderProtocol(
        runs=LONG_RUNS,
        frames=3,
        validation_runs=0,
        image_size=model.image_size,
        zero_control_fraction=1.0,
        supersample=supersample,
    )
    frames = keyvision.render(f"keycld/{scene}", protocol=protocol, seed=1, workers=1)
    images = jnp.asarray(frames.images(np.float32))
    controls = jnp.zeros((HORIZON, frames.u.shape[-1]), jnp.float32)
    dt = frames.dt

    @eqx.filter_jit
    def predict(model, images):
        x = model.encode(images)
        run = cldyn.rollout(model.dynamics, x[1], (x[2] - x[0]) / (2 * dt), controls, dt)
        return run.x, run.xd

    x, xd = jax.vmap(predict, in_axes=(None, 0))(model, images)
    energy = np.asarray(cldyn.rollout_energy(model.dynamics, x, xd), dtype=float)  # (R, HORIZON)
    potential = np.asarray(jax.vmap(jax.vmap(model.dynamics.potential_energy))(x), dtype=float)
    swing = np.ptp(potential, axis=1)
    drift = np.ptp(energy, axis=1) / swing
    t = np.arange(HORIZON) * dt
    trend = np.array([np.polyfit(t, e, 1)[0] * t[-1] for e in energy]) / swing
    strip = np.asarray(model.decode(x[0, ::STRIP_EVERY]))
    record = {
        "runs": LONG_RUNS,
        "frames": HORIZON,
        "dt": dt,
        "control": 0.0,
        "drift_over_swing": {"median": float(np.median(drift)), "max": float(drift.max())},
        "trend_over_swing": {"median": float(np.median(np.abs(trend))), "max": float(np.abs(trend).max())},
        "finite": bool(np.all(np.isfinite(energy))),
    }
    return record, (energy - energy[:, :1]) / swing[:, None], strip


def _plot_long(path: pathlib.Path, scene: str, energy: np.ndarray, strip: np.ndarray, dt: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure = plt.figure(figsize=(8, 4.4), constrained_layout=True)
    top, bottom = figure.subfigures(2, 1, height_ratios=[2.2, 1])
    axis = top.subplots()
    t = np.arange(energy.shape[1]) * dt
    for run in energy:
        axis.plot(t, run, lw=0.8)
    axis.set(
        xlabel="time (s)",
        ylabel="energy change / potential swing",
        title=f"{scene}: {energy.shape[1]} predicted frames, no control, {energy.shape[0]} runs",
    )
    cells = bottom.subplots(1, len(strip))
    for i, (cell, frame) in enumerate(zip(np.atleast_1d(cells), strip)):
        cell.imshow(np.clip(frame, 0, 1))
        cell.set_axis_off()
        cell.set_title(f"{i * STRIP_EVERY}", fontsize=7)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="SCENE=DIR",
        help="use this model of SCENE instead of the shipped one",
    )
    args = parser.parse_args()
    import jax

    import keyvision
    from keyvision._files import trained_supersample

    given = dict(item.split("=", 1) for item in args.model)
    scenes = []
    for scene in args.scenes:
        directory = pathlib.Path(given.get(scene, MODELS[scene]))
        model, spec = keyvision.load_model(directory)
        camera = trained_supersample(spec)  # the frames of the camera the model was trained on
        rows = potential(scene, model, camera)
        _plot_potential(RESULTS / f"vision_potential_{scene}.png", scene, rows)
        long, energy, strip = long_horizon(scene, model, camera)
        _plot_long(RESULTS / f"vision_long_{scene}.png", scene, energy, strip, long["dt"])
        scenes.append(
            {
                "scene": scene,
                "model": str(directory.relative_to(ROOT) if directory.is_relative_to(ROOT) else directory),
                "potential": rows,
                "long_horizon": long,
            }
        )
    result = {"machine": machine(), "device": str(jax.devices()[0]), "scenes": scenes}
    lines = [
        "# Energy in KeyCLD models learnt from images",
        "",
        "Learnt potential along posed sequences against MuJoCo's (scale and offset fitted; the paper's "
        "figures 8-12), and the learnt energy along 500-frame predictions without control "
        "(`benchmarks/vision_energy.py`). Spread where flat: along a sequence whose true potential is "
        "constant, the learnt potential's spread as a fraction of its spread along the scene's other "
        "sequence. Drift: the learnt energy's range over the prediction as a fraction of the learnt "
        "potential's swing along it; trend: a linear fit's change over the prediction, same unit.",
        "",
        "| scene | sequence | correlation | fitted scale (J per learnt unit) | learnt spread where flat |",
        "| --- | --- | --- | --- | --- |",
    ]
    for entry in scenes:
        for row in entry["potential"]:
            correlation = (
                f"{row['correlation']:.3f}" if "correlation" in row else "- (true potential constant)"
            )
            flat = f"{row['flat_fraction']:.1%}" if "flat_fraction" in row else "-"
            scale = f"{row['scale']:.3g}" if "correlation" in row else "-"
            lines.append(f"| {entry['scene']} | {row['sequence']} | {correlation} | {scale} | {flat} |")
    lines += [
        "",
        "| scene | runs x frames | energy drift / potential swing (median, max) | linear trend / swing "
        "(median, max) |",
        "| --- | --- | --- | --- |",
    ]
    for entry in scenes:
        long = entry["long_horizon"]
        drift, trend = long["drift_over_swing"], long["trend_over_swing"]
        lines.append(
            f"| {entry['scene']} | {long['runs']} x {long['frames']} | {drift['median']:.2e}, "
            f"{drift['max']:.2e} | {trend['median']:.2e}, {trend['max']:.2e} |"
        )
    lines += [""] + [
        f"![{e['scene']}](vision_potential_{e['scene']}.png) ![{e['scene']}](vision_long_{e['scene']}.png)"
        for e in scenes
    ]
    write("vision_energy", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
