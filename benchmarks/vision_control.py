"""Energy-shaping swing-up from camera frames with models learnt from images (issue 14).

For each scene and model: `keyvision.swing_up` from 20 random starts near hanging, 10 s each, the
paper's gains (kp = 5, kd = 2); the controller sees only frames rendered from MuJoCo's state, and
MuJoCo's true keypoints score the runs (success: every keypoint within 0.05 m of the upright target over
the last 0.5 s). The same runs with the true state in place of the frames' estimate (mapped into the
model's keypoint frame) measure what seeing through the camera costs. The loop's rate (render,
estimate, control) is reported against the scene's control rate.

Writes benchmarks/results/vision_control.json and .md, and vision_control_<scene>.png; prints the JSON.

    python benchmarks/vision_control.py                                   # the shipped pendulum model
    python benchmarks/vision_control.py --model cartpole=runs/cartpole-model --runs 20
"""

import argparse
import os
import pathlib
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, write  # noqa: E402


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
    args = parser.parse_args()
    import cldyn
    import keyvision
    from keyvision._cli._demo import model_directory

    models = dict(item.split("=", 1) for item in args.model) or {"pendulum": str(model_directory())}
    rows = []
    for name, directory in models.items():
        model, _ = keyvision.load_model(directory)
        results = []
        for observe in ("frames", "state"):
            result = keyvision.swing_up(
                model,
                f"keycld/{name}",
                observe=observe,
                runs=args.runs,
                duration=args.duration,
                seed=args.seed,
                keep_frames=0,
                progress_meter=cldyn.TqdmProgressMeter(),
            )
            results.append(result)
            reached = [t for t in result["time_to_tolerance"] if t is not None]
            rows.append(
                {
                    "scene": name,
                    "model": directory,
                    "observe": observe,
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
            print(rows[-1], flush=True)
        _plot(RESULTS / f"vision_control_{name}.png", results)
    # rows of scenes not run this time are kept from the previous results (one scene per call fits)
    previous = RESULTS / "vision_control.json"
    if previous.is_file():
        import json

        rows = [row for row in json.loads(previous.read_text())["rows"] if row["scene"] not in models] + rows
    result = {"machine": machine(), "kp": 5.0, "kd": 2.0, "tolerance": 0.05, "rows": rows}
    lines = [
        "# Swing-up from camera frames with models learnt from images",
        "",
        f"{args.runs} starts near hanging per scene, {args.duration:g} s each, kp = 5, kd = 2; success: "
        "every true keypoint within 0.05 m of upright over the last 0.5 s. `frames`: the controller sees "
        "only rendered frames; `state`: the true state mapped into the model's keypoint frame. Loop rate: "
        f"render + estimate + control per step on this machine ({result['machine']['cpus']} CPUs), against "
        "the scene's control rate.",
        "",
        "| scene | sees | success | median final error (m) | median time to 0.05 m (s) | loop steps/s | "
        "real time |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        reached = row["median_time_to_tolerance"]
        lines.append(
            f"| {row['scene']} | {row['observe']} | {row['success_rate']:.0%} | "
            f"{row['median_final_error']:.3f} | {'-' if reached is None else f'{reached:.2f}'} | "
            f"{row['steps_per_second']:.0f} | {row['real_time_rate']:.0f} |"
        )
    write("vision_control", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
