"""Energy-shaping swing-up from camera frames with models learnt from images (issue 14).

For each scene and model: `keyvision.swing_up` from 20 random starts near hanging, 10 s each, the
paper's gains (kp = 5, kd = 2); the controller sees only frames rendered from MuJoCo's state, and
MuJoCo's true keypoints score the runs (success: every keypoint within 0.05 m of the upright target over
the last 0.5 s). The same runs with the true state in place of the frames' estimate (mapped into the
model's keypoint frame) measure what seeing through the camera costs. The loop's rate (render,
estimate, control) and the controller's alone (estimate and control: a frame in, a command out) are
reported against the scene's control rate.

Writes benchmarks/results/vision_control.json and .md, and a plot per model (below); prints the JSON.

    python benchmarks/vision_control.py                                   # the shipped pendulum model
    python benchmarks/vision_control.py --model cartpole=runs/cartpole-model --runs 20
    python benchmarks/vision_control.py --metric mass     # gains as rates (cldyn.EnergyShaping)
    python benchmarks/vision_control.py --metric mass --trim   # minus the command at the target
    python benchmarks/vision_control.py --units si        # eq. 32's gains in SI units (camera, gears)
    python benchmarks/vision_control.py --model acrobot=DIR --supersample 4   # another camera (below)
    python benchmarks/vision_control.py --report          # the table again from the saved rows
    python benchmarks/vision_control.py --model acrobot=DIR --linearise   # the true loop at the target only

Rows are kept per scene, model directory, metric, trim, units and camera: another model of a scene adds
rows beside the others (the table names each by its directory), and its plot is
vision_control_<directory>.png with `_mass` for that metric, `_trim` for the trim, `_si` for SI units and
`_camera<N>` for a supersampled camera.

The camera renders frames as the model's training frames were rendered (`keyvision.RenderProtocol`'s
`supersample`, kept in the model's `keyvision.json`); `--supersample N` sets it: each pixel the mean of
N x N samples of MuJoCo's render, as a camera's pixel integrates light over its area.

`--metric mass` weighs the shaped potential and the damping by the learnt mass matrix: a Lagrangian
learnt from images has an arbitrary scale, and eq. 32's gains act differently at each; with the mass
metric every mode near the target obeys e'' + kd e' + kp e = 0 whatever the scale. Rows of both metrics
are kept side by side. The learnt closed loop's slowest mode at the target is reported per model, and
the true one's (the learnt controller on MuJoCo's dynamics linearised at upright, fed the state for
the state rows and the camera's reading for the frames rows): whether the target can be held at all,
and where the loop comes to rest.

`--units si` keeps eq. 32 as printed but gives kp = 5, kd = 2 in SI units, as on the true model: the
learnt model's lengths in metres (the camera's scale) and its energy in joules (the actuators' gears,
the conversion of `keyvision.identify`). It fixes the scale, not the metric: the spring still pulls on
the keypoints wherever the estimator put them on the bodies.
"""

import argparse
import os
import pathlib
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, repo_path, write  # noqa: E402


def _plot(path, results) -> None:
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 3.4), layout="constrained")
    for axis, result in zip(np.atleast_1d(axes), results):
        for errors in result["errors"]:
            axis.plot(result["ts"], errors, linewidth=0.7)
        axis.axhline(result["tolerance"], color="k", linestyle="--", linewidth=1)
        axis.set(
            yscale="log",
            xlabel="time (s)",
            ylabel="largest keypoint error (m)",
            title=f"{result['scene']} from {result['observe']}: {result['success_rate']:.0%}",
        )
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _metric(row: dict) -> str:
    return row.get("metric", "euclidean")  # rows from before the metric option: eq. 32's


def _variant(row: dict) -> tuple[str, bool, str, int]:
    """The controller of a row: its metric, whether it trims (rows from before the trim: not), the
    units its gains are given in (rows from before `--units`: the model's), and the camera's samples
    per pixel side (rows from before `--supersample`: 1, MuJoCo's render)."""
    return _metric(row), bool(row.get("trim", False)), row.get("units", "model"), row.get("supersample", 1)


def _label(row: dict) -> str:
    units = ", SI units" if row.get("units", "model") == "si" else ""
    camera = f", camera {row['supersample']}x{row['supersample']}" if row.get("supersample", 1) > 1 else ""
    return _metric(row) + units + camera + (" + trim" if row.get("trim") else "")


def _si_factor(model, scene: str, poses: int = 200, seed: int = 0, supersample: int = 1) -> dict:
    """The factor `s^2 / e` that turns eq. 32's gains given in SI units into the learnt model's units:
    `s` metres per unit of the image frame (the camera's scale), `e` joules per unit of the learnt
    energy (fixed by the actuators' gears, `keyvision.identify`'s conversion), evaluated on the
    estimator's keypoints of `poses` frames of random poses. With `x = x_SI / s`, `E = E_SI / e`, eq. 32
    `u = B_SI^+ (dV_SI - kp (x_SI - x*_SI) - kd xd_SI)` is `B^+ (dV - kp s^2/e (x - x*) - kd s^2/e xd)`."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import mujoco

    from keyvision import _control
    from keyvision._data import PlanarCamera
    from keyvision._identify import actuator_gears, energy_scale, metres_per_unit
    from keyvision._joints import joint_structure
    from keyvision._render import _scene_xml
    from keyvision._scene import _Camera

    protocol, setup = _control._model_scene(model, scene, "fixed", "si", supersample)
    physics, view = setup.model, PlanarCamera(setup.homography, setup.basis)
    data, renderer = mujoco.MjData(physics), _Camera(mujoco, setup, protocol)
    try:
        rng = np.random.default_rng(seed)
        _, frames = _control._pose_frames(mujoco, setup, data, renderer, view, rng, poses)
    finally:
        renderer.close()
    x = np.asarray(_control.encode_batch(model, frames), np.float64)
    dynamics = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, model.dynamics)
    names = [mujoco.mj_id2name(physics, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(physics.njnt)]
    structure = joint_structure(dynamics.constraint, x, names)
    metres = metres_per_unit(view)
    scale = energy_scale(dynamics, structure, x, actuator_gears(_scene_xml(scene)), metres)
    return {
        "factor": metres**2 / scale["joules_per_unit"],
        "metres_per_unit": metres,
        "joules_per_unit": scale["joules_per_unit"],
        "joules_per_unit_by_joint": scale["per_joint"],
        "spread": scale["spread"],
    }


def _supersample(args, spec: dict) -> int:
    """The camera's samples per pixel side: `--supersample`, else those of the model's training frames."""
    from keyvision._files import trained_supersample

    return args.supersample or trained_supersample(spec)


def _kind(row: dict) -> str:
    return row.get("kind", "keycld")  # rows from before the structured model: KeyCLD's


def _slowest_mode(model, target, metric: str, kp: float = 5.0, kd: float = 2.0) -> dict:
    """The learnt closed loop's slowest mode at the target: the eigenvalues of the dynamics under the
    controller, linearised on the learnt constraints' tangent space there (orthonormal basis `T`), and
    the one that decays slowest: its rate (1/s) and damping ratio."""
    import jax
    import jax.numpy as jnp

    import cldyn

    system = model.dynamics
    target = jnp.asarray(target, system.mass.matrix().dtype)
    controller = cldyn.EnergyShaping(system, target, kp, kd, metric=metric)
    k = system.size
    if system.num_constraints:
        _, _, vh = np.linalg.svd(np.asarray(system.constraint.jacobian(target), np.float64))
        tangent = vh[system.num_constraints :].T
    else:
        tangent = np.eye(k)
    acceleration = lambda x, xd: system.acceleration(x, xd, controller(0.0, x, xd))  # noqa: E731
    stiffness, damping = jax.jacfwd(acceleration, argnums=(0, 1))(target, jnp.zeros_like(target))
    d = tangent.shape[1]
    matrix = np.block(
        [
            [np.zeros((d, d)), np.eye(d)],
            [
                tangent.T @ np.asarray(stiffness, np.float64) @ tangent,
                tangent.T @ np.asarray(damping, np.float64) @ tangent,
            ],
        ]
    )
    eigenvalues = np.linalg.eigvals(matrix)
    slowest = eigenvalues[np.argmax(eigenvalues.real)]
    return {"decay_rate": float(-slowest.real), "damping_ratio": float(-slowest.real / abs(slowest))}


def _true_loops(model, name: str, kp: float, kd: float, metric: str, trim: bool, samples: int) -> dict:
    """The true loop at the target (`keyvision.target_linearisation`) as each row's controller sees
    it: `{"state": ..., "frames": ...}`."""
    import keyvision

    return {
        observe: keyvision.target_linearisation(
            model,
            f"keycld/{name}",
            observe=observe,
            kp=kp,
            kd=kd,
            metric=metric,
            trim=trim,
            supersample=samples,
        )
        for observe in ("state", "frames")
    }


def _write(rows: list) -> None:
    """benchmarks/results/vision_control.{json,md} from the rows of every scene and metric."""
    scenes = ("pendulum", "cartpole", "acrobot")
    rows = sorted(
        rows,
        # eq. 32 as printed first ("euclidean" < "mass", untrimmed before trimmed), then by scene
        key=lambda r: (_variant(r), scenes.index(r["scene"]) if r["scene"] in scenes else 9),
    )
    result = {"machine": machine(), "kp": 5.0, "kd": 2.0, "tolerance": 0.05, "rows": rows}
    lines = [
        "# Swing-up from camera frames with models learnt from images",
        "",
        f"{rows[0]['runs']} starts near hanging per scene, {rows[0]['duration']:g} s each, kp = 5, kd = 2; "
        "success: every true keypoint within 0.05 m of upright over the last 0.5 s. `frames`: the controller "
        "sees only rendered frames; `state`: the true state mapped into the model's keypoint frame. Loop "
        f"rate: render + estimate + control per step on this machine ({result['machine']['cpus']} CPUs); "
        "controller: estimate + control alone, a frame in and a command out (the render stands in for the "
        "camera); both against the scene's control rate. Metric: `euclidean` is eq. 32 as the paper prints "
        "it, its gains acting at the learnt Lagrangian's arbitrary scale; `mass` weighs the shaped potential "
        "and the damping by the learnt mass matrix, so that kp, kd are rates whatever that scale "
        "(`cldyn.EnergyShaping(metric=)`). Slowest mode: the learnt closed loop linearised at the target on "
        "the learnt constraints' tangent space, the eigenvalue that decays slowest (rate in 1/s, damping "
        "ratio); with the true model and "
        "the mass metric it is -1 +- 2j (rate 1, ratio 0.45). True loop at the target: the learnt "
        "controller on MuJoCo's dynamics, linearised at upright (`keyvision.target_linearisation`), fed "
        "what the row's controller sees: the state, or the camera's reading of postures turned by up to "
        "0.05 rad from upright (`observe=\"frames\"`; its slopes take in the estimator's warp near the "
        "target, which the state's calibration over all poses averages out): the largest real part of its "
        "eigenvalues, in 1/s; positive, the target is unstable in truth and no run can hold it. "
        "Tolerance: kp over the scene's fastest gravity rate at upright (the largest eigenvalue of M^-1 G): "
        "by how much a learnt potential's curvature there may be wrong before kp = 5 "
        "cannot hold it (mass metric, exact masses). `+ trim`: "
        "the controller subtracts its command at the target at rest (`cldyn.EnergyShaping(trim=True)`; not "
        "part of eq. 32, so these rows do not count for the paper's method). Predicted "
        "rest: where that linearised loop comes to rest (`rest_error`, the largest keypoint distance from "
        "upright; none where the true loop at the target is unstable), the median final error to compare: "
        "the learnt upright's error comes back multiplied by the gravity rate over kp. `SI "
        "units`: eq. 32 as printed with kp = 5, kd = 2 in SI units, the learnt model's lengths converted to "
        "metres by the camera's scale and its energy to joules by the actuators' gears (kp, kd times s^2/e "
        "in the model's units; `--units si`): what the paper's gains mean on the true model.",
        "",
        "| scene | model | dynamics | metric | sees | success | median final error (m) | "
        "median time to 0.05 m (s) | "
        "slowest mode: rate (1/s), ratio | true loop at the target (1/s) | predicted rest (m) | tolerance | "
        "loop steps/s | controller frames/s | real time |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        reached, mode = row["median_time_to_tolerance"], row.get("slowest_mode")
        mode = "-" if mode is None else f"{mode['decay_rate']:.2f}, {mode['damping_ratio']:.2f}"
        truth = row.get("true_target")
        if truth is None:
            truth = "- | - | -"
        else:
            rest = truth.get("rest_error")
            if truth["largest_real_part"] > 0:
                rest = "none (unstable)"  # an equilibrium the loop leaves, not a rest
            elif rest is not None:
                rest = f"{rest:.3f}"
            else:
                rest = "-"
            # kp over the fastest gravity rate for kp = 5 (a row in SI units ran 5 s^2/e in the model's)
            tolerance = truth["curvature_tolerance"] / (row.get("si_conversion") or {}).get("factor", 1.0)
            truth = f"{truth['largest_real_part']:+.2f} | {rest} | {tolerance:.0%}"
        lines.append(
            f"| {row['scene']} | {pathlib.Path(row['model']).name} | {_kind(row)} | {_label(row)} | "
            f"{row['observe']} | "
            f"{row['success_rate']:.0%} | "
            f"{row['median_final_error']:.3f} | {'-' if reached is None else f'{reached:.2f}'} | {mode} | "
            f"{truth} | "
            f"{row['steps_per_second']:.0f} | {1.0 / row['seconds_per_step']['policy_per_step']:.0f} | "
            f"{row['real_time_rate']:.0f} |"
        )
    write("vision_control", result, "\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="SCENE=DIR",
        help="a model of keycld/SCENE (default: pendulum=the model shipped with keyvision demo)",
    )
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--metric", choices=("euclidean", "mass"), default="euclidean")
    parser.add_argument(
        "--trim",
        action="store_true",
        help="subtract the controller's command at the target (cldyn.EnergyShaping(trim=True); not eq. 32)",
    )
    parser.add_argument(
        "--units",
        choices=("model", "si"),
        default="model",
        help="the units kp, kd are given in: the learnt model's (eq. 32 as printed) or SI, the model's "
        "lengths in metres by the camera's scale and its energy in joules by the actuators' gears "
        "(with --metric euclidean; the mass metric does not depend on units)",
    )
    parser.add_argument(
        "--supersample",
        type=int,
        help="the camera's samples per pixel side (keyvision.RenderProtocol); default: those of the frames "
        "each model was trained on",
    )
    parser.add_argument(
        "--report", action="store_true", help="run nothing: rewrite the table from the saved rows"
    )
    parser.add_argument(
        "--linearise",
        action="store_true",
        help="no swing-ups: the true loop at the target (keyvision.target_linearisation) of each --model, "
        "added to its saved rows of this --metric",
    )
    args = parser.parse_args()
    if args.units == "si" and args.metric != "euclidean":
        parser.error("--units si goes with --metric euclidean (the mass metric does not depend on units)")
    if args.supersample is not None and args.supersample < 1:
        parser.error(f"--supersample must be at least 1, got {args.supersample}")
    if args.report:
        import json

        _write(json.loads((RESULTS / "vision_control.json").read_text())["rows"])
        return
    import cldyn
    import keyvision
    from keyvision._cli._demo import model_directory

    models = dict(item.split("=", 1) for item in args.model) or {"pendulum": str(model_directory())}
    if args.linearise:
        import json

        rows = json.loads((RESULTS / "vision_control.json").read_text())["rows"]
        for name, directory in models.items():
            model, spec = keyvision.load_model(directory)
            samples = _supersample(args, spec)
            variant = (args.metric, args.trim, args.units, samples)
            factor = 1.0
            if args.units == "si":
                factor = _si_factor(model, f"keycld/{name}", supersample=samples)["factor"]
            truths = _true_loops(model, name, 5.0 * factor, 2.0 * factor, args.metric, args.trim, samples)
            print(name, directory, variant, truths, flush=True)
            key = (name, repo_path(directory), variant)
            matched = [r for r in rows if (r["scene"], repo_path(r["model"]), _variant(r)) == key]
            if not matched:
                raise SystemExit(
                    f"no saved rows of {name}={directory} with --metric {args.metric}"
                    + (" --trim" if args.trim else "")
                    + (" --units si" if args.units == "si" else "")
                )
            for row in matched:
                row["true_target"] = truths[row["observe"]]
        _write(rows)
        return
    new, run = [], set()
    for name, directory in models.items():
        model, spec = keyvision.load_model(directory)
        kind = spec["dynamics"]["kind"]
        samples = _supersample(args, spec)
        run.add((name, repo_path(directory), (args.metric, args.trim, args.units, samples)))
        si = _si_factor(model, f"keycld/{name}", supersample=samples) if args.units == "si" else None
        kp, kd = (5.0, 2.0) if si is None else (5.0 * si["factor"], 2.0 * si["factor"])
        truths = _true_loops(model, name, kp, kd, args.metric, args.trim, samples)
        results = []
        for observe in ("frames", "state"):
            result = keyvision.swing_up(
                model,
                f"keycld/{name}",
                observe=observe,
                kp=kp,
                kd=kd,
                metric=args.metric,
                trim=args.trim,
                runs=args.runs,
                duration=args.duration,
                seed=args.seed,
                supersample=samples,
                keep_frames=0,
                progress_meter=cldyn.TqdmProgressMeter(),
            )
            results.append(result)
            reached = [t for t in result["time_to_tolerance"] if t is not None]
            new.append(
                {
                    "scene": name,
                    "model": repo_path(directory),
                    "kind": kind,
                    "observe": observe,
                    "metric": args.metric,
                    "trim": args.trim,
                    "units": args.units,
                    "supersample": samples,
                    "gains_in_model_units": [kp, kd],
                    "si_conversion": si,
                    "slowest_mode": _slowest_mode(model, result["target_keypoints"], args.metric, kp, kd),
                    "true_target": truths[observe],
                    "runs": args.runs,
                    "duration": args.duration,
                    "success_rate": result["success_rate"],
                    "median_final_error": float(np.median(result["final_error"])),
                    "median_time_to_tolerance": float(np.median(reached)) if reached else None,
                    "steps_per_second": result["steps_per_second"],
                    "real_time_rate": result["real_time_rate"],
                    "seconds_per_step": result["seconds"],
                }
            )
            print(new[-1], flush=True)
        suffix = ("" if args.metric == "euclidean" else f"_{args.metric}") + ("_trim" if args.trim else "")
        suffix += ("_si" if args.units == "si" else "") + (f"_camera{samples}" if samples > 1 else "")
        _plot(RESULTS / f"vision_control_{pathlib.Path(directory).name}{suffix}.png", results)
    # rows of the models and metrics not run this time are kept from the previous results (one scene
    # per call fits)
    rows, previous = [], RESULTS / "vision_control.json"
    if previous.is_file():
        import json

        rows = [
            r
            for r in json.loads(previous.read_text())["rows"]
            if (r["scene"], repo_path(r["model"]), _variant(r)) not in run
        ]
    _write(rows + new)


if __name__ == "__main__":
    main()
