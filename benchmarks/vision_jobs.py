"""How many `keyvision train` processes to run at once on this machine: the training rate of 1, 2, ...
concurrent trainings, each measured against one training alone in the same run.

`benchmarks/vision_table.py --jobs N` runs N trainings at once, each its own process. On a GPU small
models leave most of the device idle and several share it well; on a CPU the processes share its cores,
and whether that gains anything depends on how well one training already uses them. Each training here is
the table's recipe (`benchmarks/vision.py`'s options, the same networks, batches and frames) cut to a few
steps of the two stages that take its time: stage (a), the autoencoder on single frames (200 steps by
default), and stage (c), everything trained on windows of frames (150; stages (b) and (d), the dynamics
on keypoints, take a few per cent of a training and get no steps). A stage's rate is taken from its
history between its first record and its last before the final validation, so compilation and validation,
which a full training pays once, are not counted. For N trainings at once, the throughput is the sum of
their rates over the rate of one training alone: above 1, N at once finish N trainings sooner than one
after another.

    python benchmarks/vision_jobs.py                 # 1 and 2 at once, on the cart-pole's frames
    python benchmarks/vision_jobs.py --jobs 1 2 3    # up to 3

Uses the table's cart-pole frames (`runs/bench-vision-table/cartpole/data`) when they exist, else
renders 40 runs (`keyvision render`, about a minute and a half on 2 CPU cores). Writes
benchmarks/results/vision_jobs.{json,md} and prints the JSON.
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import machine, write  # noqa: E402
from vision import _cli, add_recipe, recipe_options  # noqa: E402

STAGES = ("autoencoder", "joint")  # the stages timed (the others get no steps)


def _rate(model: pathlib.Path, stage: str) -> float:
    """Steps per second of `stage` from its first record to its last without a validation loss (the
    first chunk's compilation and the final validation are not counted)."""
    records = [
        r
        for r in json.loads((model / f"history-{stage}.json").read_text())["records"]
        if "validation" not in r
    ]
    if len(records) < 2 or records[-1]["seconds"] <= records[0]["seconds"]:
        raise SystemExit(
            f"vision_jobs: {model}: stage {stage} has too few records to time; give it more steps"
        )
    first, last = records[0], records[-1]
    return (last["step"] - first["step"]) / (last["seconds"] - first["seconds"])


def _train_at_once(jobs: int, data: pathlib.Path, options: list, work: pathlib.Path) -> dict:
    """Start `jobs` trainings (seeds 0, 1, ...) together; their stage rates and wall times."""
    started, processes = time.perf_counter(), []
    for seed in range(jobs):
        out = work / f"jobs{jobs}-seed{seed}"
        command = [sys.executable, "-m", "keyvision", "train", "--data", str(data), "--out", str(out)]
        command += [str(o) for o in options] + ["--seed", str(seed), "--no-progress", "--overwrite"]
        log = open(work / f"jobs{jobs}-seed{seed}.log", "w")
        processes.append((out, subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT), log))
    ended = {}  # each training's own wall time, taken when it ends, whichever ends first
    while len(ended) < len(processes):
        for index, (_, process, _) in enumerate(processes):
            if index not in ended and process.poll() is not None:
                ended[index] = round(time.perf_counter() - started, 1)
        time.sleep(0.2)
    trainings = []
    for index, (out, process, log) in enumerate(processes):
        status = process.returncode
        log.close()
        if status != 0:
            tail = pathlib.Path(log.name).read_text()[-2000:]
            raise SystemExit(f"vision_jobs: keyvision train failed with status {status}:\n{tail}")
        rates = {stage: _rate(out, stage) for stage in STAGES}
        trainings.append({"steps_per_second": rates, "wall_seconds": ended[index]})
    return {"trainings": trainings, "seconds": round(time.perf_counter() - started, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--jobs", type=int, nargs="+", default=[1, 2], help="trainings at once, each measured"
    )
    parser.add_argument("--data", default=None, help="frames.npz or its directory (default: see above)")
    add_recipe(parser, autoencoder_steps=200, dynamics_steps=0, joint_steps=150, refit_steps=0, rounds=1)
    args = parser.parse_args()
    if min(args.jobs) < 1 or 1 not in args.jobs:
        parser.error("--jobs: counts of at least 1, and 1 among them (the reference)")
    for name in ("autoencoder_steps", "joint_steps"):
        if getattr(args, name) < 150:
            parser.error(
                f"--{name.replace('_', '-')}: at least 150 (two records 50 steps apart before the last)"
            )
    if args.candidates != 1:
        parser.error("--candidates: 1 (the trials of several candidates are stage (a) again)")
    data = (
        pathlib.Path(args.data) if args.data else ROOT / "runs" / "bench-vision-table" / "cartpole" / "data"
    )
    if not args.data and not (data / "frames.npz").is_file():
        data = ROOT / "runs" / "bench-vision-jobs" / "data"
        if not (data / "frames.npz").is_file():
            _cli("render", "--scene", "keycld/cartpole", "--out", data, "--runs", 40)
    options = recipe_options(args)
    results = {}
    with tempfile.TemporaryDirectory(prefix="vision-jobs-") as work:
        for jobs in sorted(set(args.jobs)):
            print(f"vision_jobs: {jobs} at once ...", file=sys.stderr, flush=True)
            results[jobs] = _train_at_once(jobs, data, options, pathlib.Path(work))
    alone = results[1]["trainings"][0]["steps_per_second"]
    rows = {}
    for jobs, result in results.items():
        rates = [t["steps_per_second"] for t in result["trainings"]]
        rows[str(jobs)] = {
            **result,
            "throughput_vs_one_alone": {
                stage: round(sum(r[stage] for r in rates) / alone[stage], 3) for stage in STAGES
            },
        }
    shown = data.resolve().relative_to(ROOT) if data.resolve().is_relative_to(ROOT) else data
    info = machine()
    result = {
        "machine": info,
        "data": str(shown),
        "recipe": options,
        "note": "throughput: the summed steps per second of N trainings at once over one training's alone, "
        "per stage, compilation excluded",
        "jobs": rows,
    }
    lines = [
        "# Trainings at once on this machine (`benchmarks/vision_jobs.py`)",
        "",
        f"{info['cpus']} CPUs, jax {info['jax']} ({info['backend']}); the table's recipe on "
        f"`{shown}`, {args.autoencoder_steps} steps of stage (a) and {args.joint_steps} of stage (c).",
        "",
        "| at once | stage (a) steps/s each | stage (c) steps/s each | throughput (a), (c) vs one alone "
        "| wall (s) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for jobs, row in rows.items():
        each = {s: " / ".join(f"{t['steps_per_second'][s]:.2f}" for t in row["trainings"]) for s in STAGES}
        gain = row["throughput_vs_one_alone"]
        lines.append(
            f"| {jobs} | {each['autoencoder']} | {each['joint']} "
            f"| {gain['autoencoder']:.2f}, {gain['joint']:.2f} | {row['seconds']:.0f} |"
        )
    write("vision_jobs", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
