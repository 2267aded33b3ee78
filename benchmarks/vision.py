"""KeyCLD from images: render, train and evaluate on the KeyCLD scenes; VPT, wall time, images/s.

For each scene (a KeyCLD scene's name, or an MJCF file: a scene that is not KeyCLD's, whose
constraints `keyvision train` reads from it, `keyvision.scene_constraint`; its row is named after the
file): `keyvision render` (the paper's protocol, or fewer runs), `keyvision train` (the stages
of `keyvision.train` with the sizes and steps given here; the defaults are the CPU recipe of
docs/images.md) and `keyvision evaluate` (VPT over the validation runs, the autoencoder's ceiling, the
error over time, a frame strip and a GIF). `--model SCENE=DIR` evaluates a model trained elsewhere
instead of training one. A step whose outputs already exist in
`--out` is not run again (a finished training is reused; an interrupted one is resumed), so a budget
can be spread over several calls. Training images/s counts the frames that pass through the estimator
in a training step (stage (a): the batch; stage (c): windows x frames), over the stages' wall time.

Writes benchmarks/results/vision.json and vision.md (scenes not given keep their previous rows), copies
each scene's mse.png, strip.png and prediction.gif to benchmarks/results/vision_<scene>_*; prints the
JSON.

    python benchmarks/vision.py                       # the three scenes, the CPU recipe
    python benchmarks/vision.py --scenes pendulum --model pendulum=runs/pend
    python benchmarks/vision.py --scenes benchmarks/mechanisms/chain3.xml --rounds 1
"""

import argparse
import json
import os
import pathlib
import shutil
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, repo_path, write  # noqa: E402

PAPER_VPT = {"pendulum": 0.38, "cartpole": 1.00, "acrobot": 1.00}  # Table 1, KeyCLD


def _cli(*argv) -> None:
    from cldyn._cli._common import INTERRUPTED  # a command's exit status when stopped by SIGINT
    from keyvision._cli import main

    status = main([str(a) for a in argv])
    if status == INTERRUPTED:  # Ctrl-C: the benchmark stops too (not a failed step to record)
        raise KeyboardInterrupt
    if status != 0:
        raise SystemExit(f"keyvision {argv[0]} failed with status {status}")


# the options of `keyvision train` that make the CPU recipe of docs/images.md, with its values
RECIPE = {
    "width": (int, 16),
    "autoencoder_steps": (int, 3000),
    "autoencoder_batch": (int, 16),
    "dynamics_steps": (int, 2000),
    "joint_steps": (int, 600),
    "joint_batch": (int, 4),
    "refit_steps": (int, 2000),
    "rounds": (int, 2),
    "window": (int, 10),
    "joint_lr": (float, 3e-4),
    "heatmap_weight": (float, 0.0),
    "dynamics_weight": (float, 60.0),
    "constraint_weight": (float, 10.0),
    "constraint_drift": (str, "window"),
    "candidates": (int, 1),
    "candidate_steps": (int, 500),
    "candidate_runs": (int, 50),
}


def add_recipe(parser: argparse.ArgumentParser, **defaults) -> None:
    """Add the recipe's options to a benchmark's parser (`defaults` overrides some of its values)."""
    for name, (kind, default) in RECIPE.items():
        parser.add_argument(f"--{name.replace('_', '-')}", type=kind, default=defaults.get(name, default))
    parser.add_argument(
        "--augment",
        action="store_true",
        help="train the estimator on frames turned and mirrored at random (`keyvision train --augment`)",
    )


def recipe_options(args) -> list:
    """The recipe's options as `keyvision train` arguments."""
    options = [item for name in RECIPE for item in (f"--{name.replace('_', '-')}", getattr(args, name))]
    return options + (["--augment"] if getattr(args, "augment", False) else [])


def _images_per_second(stages: dict, schedule: dict) -> float | None:
    frames = 0
    seconds = 0.0
    for stage, record in stages.items():
        if stage == "autoencoder":
            per_step = schedule["autoencoder_batch"]
        elif stage.startswith("joint"):
            per_step = schedule["joint_batch"] * schedule["window"]
        else:
            continue  # the dynamics stages see keypoints, not images
        if record["steps"] and record["seconds"]:
            frames += record["steps"] * per_step
            seconds += record["seconds"]
    return frames / seconds if seconds else None


def _scene_name(scene: str) -> str:
    """A row's name: the KeyCLD scene's, or an MJCF file's stem."""
    return pathlib.Path(scene).stem if scene.endswith(".xml") else scene


def scene(source: str, args) -> dict:
    name = _scene_name(source)
    out = pathlib.Path(args.out) / name
    data, model, evaluation = out / "data", out / "model", out / "evaluate"
    if not (data / "frames.npz").is_file():
        mjcf = source if source.endswith(".xml") else f"keycld/{name}"
        _cli("render", "--scene", mjcf, "--out", data, "--runs", args.runs)
    given = dict(item.split("=", 1) for item in args.model).get(name)
    if given is not None:
        model = pathlib.Path(given)
    trained = model / "model.eqx"
    started = time.perf_counter()
    if not trained.is_file():
        if given is not None:
            raise SystemExit(f"--model {name}={given}: no model.eqx there")
        options = ["--data", data, "--out", model, "--seed", args.seed, *recipe_options(args)]
        resume = ["--resume"] if (model / "keyvision.json").is_file() else []
        _cli("train", *options, *resume)
    train_seconds = time.perf_counter() - started
    _cli("evaluate", "--model", model, "--data", data, "--out", evaluation, "--overwrite")
    spec = json.loads((model / "keyvision.json").read_text())
    vpt = json.loads((evaluation / "vpt.json").read_text())
    stages = {}
    for history in sorted(model.glob("history-*.json"), key=lambda path: path.stat().st_mtime):
        records = json.loads(history.read_text())["records"]
        last = records[-1] if records else {}
        stage = history.stem.removeprefix("history-")
        stages[stage] = {"steps": last.get("step"), "seconds": last.get("seconds")}
    for figure in ("mse.png", "strip.png", "prediction.gif"):
        shutil.copyfile(evaluation / figure, RESULTS / f"vision_{name}_{figure}")
    return {
        "scene": name,
        "model": repo_path(model),
        "vpt": vpt["vpt"],
        "autoencoder": vpt.get("autoencoder"),
        "paper_vpt": PAPER_VPT.get(name),
        "keypoint_tracking_r2": vpt.get("keypoint_tracking_r2"),
        "keypoint_error_px": vpt.get("keypoint_error_px"),
        "constraint_drift_px": vpt.get("constraint_drift_px"),
        "keypoint_motion": vpt.get("keypoint_motion"),
        "validation_runs": vpt["runs"],
        "image_size": spec["image_size"],
        "width": spec["width"],
        "schedule": spec["schedule"],
        "training_runs": spec.get("data", {}).get("runs"),
        "train": {"stages": stages, "seconds_this_call": round(train_seconds, 1)},
        "images_per_second": _images_per_second(stages, spec["schedule"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["pendulum", "cartpole", "acrobot"])
    parser.add_argument("--out", default=str(ROOT / "runs" / "bench-vision"))
    parser.add_argument("--runs", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    add_recipe(parser)
    parser.add_argument(
        "--note", default=None, help="a paragraph under the table (default: the previous results' note)"
    )
    parser.add_argument(
        "--model", action="append", default=[], metavar="SCENE=DIR", help="evaluate this model of SCENE"
    )
    args = parser.parse_args()
    import jax

    rows = [scene(name, args) for name in args.scenes]
    # the scenes not run this time keep their rows of the previous results (scene order kept)
    previous = RESULTS / "vision.json"
    note = args.note
    if previous.is_file():
        earlier = json.loads(previous.read_text())
        note = earlier.get("note", "") if note is None else note
        kept = {row["scene"]: row for row in earlier.get("scenes", [])}
        kept.update({row["scene"]: row for row in rows})
        order = [*PAPER_VPT, *sorted(set(kept) - set(PAPER_VPT))]  # KeyCLD's scenes first
        rows = sorted(kept.values(), key=lambda row: order.index(row["scene"]))
    result = {"machine": machine(), "device": str(jax.devices()[0]), "scenes": rows, "note": note or ""}
    lines = [
        "# KeyCLD from images",
        "",
        f"Device: {result['device']} ({result['machine']['cpus']} CPUs). VPT over the validation runs "
        "(the paper's eq. 16); ceiling: the VPT of frames redrawn from their own estimated keypoints "
        "(the autoencoder alone, perfect dynamics); R^2: keypoint tracking (affine map to the true pose, "
        "held out; a pose feature of a second link is not affine in the keypoints, so it reads low on the "
        "acrobot); error: held-out RMS pixels between the keypoints and MuJoCo's after an affine fit, per "
        "keypoint; drift: the RMS standard deviation of each constraint's value along a run of estimated "
        "keypoints, in pixels (0 for keypoints on rigid points of the bodies); training: the stages' wall "
        "time as their histories recorded it; motion: how far each keypoint moves over how far MuJoCo's "
        "moves (near 0 for a keypoint that stands still, which the error and the drift cannot see; rows of "
        "earlier runs lack it).",
        "",
        "| scene | VPT mean | median | std | paper | ceiling | R^2 | error (px) | drift (px) | motion "
        "| frames | width | training (s) | images/s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        seconds = sum((s["seconds"] or 0) for s in row["train"]["stages"].values())
        r2 = row["keypoint_tracking_r2"]
        rate = row["images_per_second"]
        vpt, size = row["vpt"], row["image_size"]
        cells = [row["scene"], f"{vpt['mean']:.3f}", f"{vpt['median']:.3f}", f"{vpt['std']:.3f}"]
        ceiling = (row["autoencoder"] or {}).get("vpt", {}).get("mean")
        paper = "-" if row["paper_vpt"] is None else f"{row['paper_vpt']:.2f}"
        cells += [paper, "-" if ceiling is None else f"{ceiling:.3f}"]
        error = row["keypoint_error_px"]
        cells += ["-" if r2 is None else f"{r2:.3f}"]
        drift = row["constraint_drift_px"]
        cells += ["-" if error is None else " / ".join(f"{e:.2f}" for e in error)]
        motion = row.get("keypoint_motion")
        cells += ["-" if drift is None else " / ".join(f"{e:.2f}" for e in drift)]
        cells += ["-" if motion is None else " / ".join(f"{m:.2f}" for m in motion), f"{size}x{size}"]
        cells += [str(row["width"]), f"{seconds:.0f}", "-" if rate is None else f"{rate:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    if result["note"]:
        lines += ["", result["note"]]
    write("vision", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
