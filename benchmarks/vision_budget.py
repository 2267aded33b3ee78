"""VPT per hour of training: one `keyvision train` evaluated after every stage that completes a model.

A training of `keyvision train` holds each stage's model (`model-<stage>.eqx`) and history; the model is
complete (networks and fitted dynamics) after stage (b), `dynamics`, and after every round's `refit`
stage. For each of those this script runs `keyvision evaluate --stage` on the validation runs and
pairs its VPT with the training's wall time up to the end of that stage (the stages' histories), so
the VPT that the recipe reaches per hour of training is measured on one training, not assembled from
several. It can be run while the training still goes on: it evaluates the stages finished so far, and
a stage already evaluated in `--out` is not evaluated again.

Writes benchmarks/results/vision_budget_<scene>.{json,md} and vision_budget_<scene>.png (VPT against
hours of training, the paper's VPT dashed); prints the JSON.

    python benchmarks/vision_budget.py --scene cartpole --model runs/cart-budget --data runs/cartpole-data
"""

import argparse
import json
import os
import pathlib
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, write  # noqa: E402
from vision import PAPER_VPT, _cli  # noqa: E402


def _stage_seconds(model: pathlib.Path, stage: str) -> float | None:
    """The wall time of a finished stage, from its history (None while it has not finished)."""
    if not (model / f"model-{stage}.eqx").is_file():
        return None
    records = json.loads((model / f"history-{stage}.json").read_text())["records"]
    return float(records[-1]["seconds"]) if records else 0.0


def _plot(path: pathlib.Path, scene: str, points: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hours = [p["training_seconds"] / 3600 for p in points]
    figure, axes = plt.subplots(figsize=(5, 3.2), constrained_layout=True)
    axes.plot(hours, [p["vpt"]["mean"] for p in points], "o-", label="VPT mean")
    axes.plot(hours, [p["vpt"]["median"] for p in points], "s--", label="VPT median")
    for hour, point in zip(hours, points):
        axes.annotate(
            point["stage"],
            (hour, point["vpt"]["mean"]),
            textcoords="offset points",
            xytext=(4, -12),
            fontsize=7,
        )
    axes.axhline(PAPER_VPT[scene], color="k", linestyle=":", label="paper (Table 1)")
    axes.set(xlabel="hours of training (2-core CPU)", ylabel="VPT", ylim=(0, 1.05), title=scene)
    axes.legend(fontsize=8, loc="lower right")
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", required=True, choices=sorted(PAPER_VPT))
    parser.add_argument("--model", required=True, help="the directory of a keyvision train (finished or not)")
    parser.add_argument("--data", required=True, help="the frames it was trained on (their validation runs)")
    parser.add_argument("--out", default=None, help="evaluations (default: runs/bench-vision-budget/<scene>)")
    parser.add_argument("--note", default="", help="a sentence on the machine's load during the training")
    args = parser.parse_args()
    from keyvision._train import stages_run

    model = pathlib.Path(args.model)
    out = pathlib.Path(args.out or ROOT / "runs" / "bench-vision-budget" / args.scene)
    spec = json.loads((model / "keyvision.json").read_text())
    # a training that started from another's autoencoder (--networks-from) counts that stage's time
    points, elapsed = [], float((spec.get("networks_from") or {}).get("autoencoder_seconds") or 0.0)
    for stage in stages_run(spec["schedule"]):
        seconds = _stage_seconds(model, stage)
        if seconds is None:
            break  # not trained (yet)
        elapsed += seconds
        if stage != "dynamics" and not stage.startswith("refit"):
            continue  # the networks of this stage still wait for their dynamics to be fitted
        evaluation = out / stage
        if not (evaluation / "vpt.json").is_file():
            _cli(
                "evaluate",
                "--model",
                model,
                "--stage",
                stage,
                "--data",
                args.data,
                "--out",
                evaluation,
                "--overwrite",
            )
        vpt = json.loads((evaluation / "vpt.json").read_text())
        points.append(
            {
                "stage": stage,
                "training_seconds": round(elapsed, 1),
                "vpt": vpt["vpt"],
                "autoencoder_vpt": (vpt.get("autoencoder") or {}).get("vpt", {}).get("mean"),
                "keypoint_error_px": vpt.get("keypoint_error_px"),
                "constraint_drift_px": vpt.get("constraint_drift_px"),
            }
        )
    if not points:
        raise SystemExit(f"{model}: no stage that completes a model has finished yet")
    import jax

    result = {
        "machine": machine(),
        "device": str(jax.devices()[0]),
        "scene": args.scene,
        "model": str(model),
        "schedule": spec["schedule"],
        "paper_vpt": PAPER_VPT[args.scene],
        "note": args.note,
        "points": points,
    }
    name = f"vision_budget_{args.scene}"
    _plot(RESULTS / f"{name}.png", args.scene, points)
    lines = [
        f"# VPT per hour of training: {args.scene}",
        "",
        f"One `keyvision train` ({model}) evaluated after each stage that completes a model, on the 50 "
        f"validation runs; training time: the stages' wall time up to that stage, from their histories. "
        f"Device: {result['device']} ({result['machine']['cpus']} CPUs). Paper (Table 1): "
        f"{PAPER_VPT[args.scene]:.2f}. {args.note}".rstrip(),
        "",
        "| after stage | training (h) | VPT mean | median | std | autoencoder ceiling "
        "| keypoint error (px) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for point in points:
        hours = point["training_seconds"] / 3600
        vpt, error = point["vpt"], point["keypoint_error_px"]
        cells = [
            point["stage"],
            f"{hours:.2f}",
            f"{vpt['mean']:.3f}",
            f"{vpt['median']:.3f}",
            f"{vpt['std']:.3f}",
            "-" if point["autoencoder_vpt"] is None else f"{point['autoencoder_vpt']:.3f}",
            "-" if error is None else " / ".join(f"{e:.2f}" for e in error),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"![VPT against hours of training]({name}.png)"]
    write(name, result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
