"""The paper's ablation study from images (Table 1, Fig. 3, Figs. 4 and 13-15) in one command.

For each scene: the frames of `keyvision render` (the paper's protocol), then these models, each trained
by `keyvision train` with the same recipe (`benchmarks/vision.py`'s options) and evaluated by
`keyvision evaluate` on the 50 validation runs:

- KeyCLD, `--seeds` seeds (each its own autoencoder);
- KeyCLD-NC (no constraints), NODE2 (a second-order neural ODE), KeyCLD with coupled constant masses and
  the structured model (coupled masses, a linear potential, joint motors; no networks in the dynamics):
  the dynamics differ, the estimator and renderer do not, so these start from the autoencoder stage of
  KeyCLD's first seed (`keyvision train --networks-from`) and their training time counts that stage;
- FC: KeyCLD's dynamics with the FC estimator and renderer (`--networks fc`, its own autoencoder).

Every step is skipped when its output exists (a finished training is reused, an interrupted one
resumed), so the budget can be spread over several calls. `--jobs N` runs N trainings and evaluations at
once, each a `keyvision train` or `keyvision evaluate` process of its own (an ablation waits for the
autoencoder stage it starts from; a model is evaluated as soon as it is trained): on a
GPU, small models leave most of it idle, and several trainings share it well; on 2 CPU cores two at
once train at 1.3-1.4 times the rate of one (`benchmarks/vision_jobs.py`).
Each model trained here records `device.json`: the device, how many trainings ran at once, the wall
time of its training process. Writes benchmarks/results/vision_table.{json,md}
(the paper's Table 1 layout: VPT mean +- std over the validation runs and the median, KeyCLD's seeds
pooled, the paper's values beside), vision_table_mse_<scene>.png (Fig. 3: MSE over time, quartile
bands, the threshold dashed) and vision_table_frames_<scene>.png (Figs. 4, 13-15: every fourth frame of
one validation run, true and as each model predicts it); prints the JSON. With `--augment` (every
model's estimator trained on frames turned and mirrored at random) the same table is a table of its own:
its models in `runs/bench-vision-table-augmented`, its results in vision_table_augmented*.

    python benchmarks/vision_table.py --scenes pendulum --rounds 1   # the CPU budget of the table
    python benchmarks/vision_table.py --scenes pendulum --models KeyCLD NODE2   # some rows only
    python benchmarks/vision_table.py --report     # the table of what has finished, training nothing
    python benchmarks/vision_table.py --seeds 3 --ablation-seeds 3 --jobs 6   # on one GPU
    python benchmarks/vision_table.py --augment --seeds 3 --ablation-seeds 3 --jobs 6   # augmented
"""

import argparse
import contextlib
import io
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, repo_path, write  # noqa: E402
from _table_figures import errors, plot_frames, plot_mse  # noqa: E402
from vision import _cli, add_recipe, recipe_options  # noqa: E402

# Table 1 of the paper (VPT)
PAPER = {
    "KeyCLD": {"pendulum": 0.38, "cartpole": 1.00, "acrobot": 1.00},
    "KeyCLD-NC": {"pendulum": 0.20, "cartpole": 0.48, "acrobot": 0.50},
    "NODE2": {"pendulum": 0.12, "cartpole": 0.26, "acrobot": 0.44},
    "FC": {"pendulum": 0.00, "cartpole": 0.10, "acrobot": 0.00},
}
# row -> the `keyvision train` options that make it, and whether it shares KeyCLD's autoencoder
VARIANTS = {
    "KeyCLD coupled mass": (["--model", "keycld-coupled"], True),
    "KeyCLD structured": (["--model", "keycld-structured"], True),
    "KeyCLD-NC": (["--model", "nc"], True),
    "NODE2": (["--model", "node2"], True),
    "FC": (["--networks", "fc"], False),
}


def _seconds(model: pathlib.Path) -> float:
    """A training's wall time: its stages' histories, plus the shared autoencoder it started from."""
    total = 0.0
    for history in model.glob("history-*.json"):
        records = json.loads(history.read_text())["records"]
        total += float(records[-1]["seconds"]) if records else 0.0
    shared = json.loads((model / "keyvision.json").read_text()).get("networks_from")
    return total + float((shared or {}).get("autoencoder_seconds") or 0.0)


class _Tee(io.StringIO):
    """Writes through to `stream` and keeps a copy (a failed command's error line, for the table)."""

    def __init__(self, stream):
        super().__init__()
        self.stream = stream

    def write(self, text: str) -> int:
        self.stream.write(text)
        return super().write(text)


def _last_stage(model: pathlib.Path) -> str | None:
    """The last stage of an unfinished training that left a model, in training order."""
    from keyvision._train import stage_names

    order = ["autoencoder", "dynamics", *(n for r in range(1, 10) for n in stage_names(r))]
    done = [stage for stage in order if (model / f"model-{stage}.eqx").is_file()]
    return done[-1] if done else None


def _stopped(model: pathlib.Path) -> dict | None:
    """What `stopped.json` says of a training that stopped before its end, or None."""
    stopped = model / "stopped.json"
    return json.loads(stopped.read_text()) if stopped.is_file() else None


def _trained(model: pathlib.Path) -> bool:
    """Whether a training is over: finished, or stopped before its end (`stopped.json`)."""
    return (model / "model.eqx").is_file() or (model / "stopped.json").is_file()


def _train_arguments(model: pathlib.Path, data: pathlib.Path, options: list) -> list:
    resume = ["--resume"] if (model / "keyvision.json").is_file() else []
    return ["train", "--data", data, "--out", model, *options, *resume, "--no-progress"]


def _record_stop(model: pathlib.Path, said: str, error) -> bool:
    """After a failed training: `stopped.json` when a stage had finished (so that later calls do not
    train it again, and that stage's model is evaluated in its place); False when none had."""
    stage = _last_stage(model)
    if stage is None:
        return False
    errors = [line for line in said.splitlines() if "error:" in line]
    note = {"error": errors[-1] if errors else str(error), "evaluated_stage": stage}
    (model / "stopped.json").write_text(json.dumps(note, indent=1) + "\n")
    print(f"{model}: the training stopped ({error}); evaluating its {stage} stage", flush=True)
    return True


def _record_device(model: pathlib.Path, device: str, jobs: int, seconds: float) -> None:
    record = {"device": device, "concurrent_trainings": jobs, "wall_seconds": round(seconds, 1)}
    (model / "device.json").write_text(json.dumps(record, indent=1) + "\n")


def _train_and_evaluate(model: pathlib.Path, data: pathlib.Path, options: list, device: str) -> dict:
    """Train (or resume) and evaluate one model. A training that stops (a diverging stage) is a result
    too: recorded in `stopped.json` (so that later calls do not train it again) and the model of its
    last finished stage is evaluated in its place."""
    if not _trained(model):
        errors = _Tee(sys.stderr)
        started = time.perf_counter()
        try:
            with contextlib.redirect_stderr(errors):
                _cli(*_train_arguments(model, data, options))
        except SystemExit as error:
            if not _record_stop(model, errors.getvalue(), error):
                raise
        _record_device(model, device, 1, time.perf_counter() - started)
    note = _stopped(model)
    if not _finished(model):
        _cli(*_evaluate_arguments(model, data))
    vpt = json.loads((_evaluation(model) / "vpt.json").read_text())
    trained_on = model / "device.json"
    on = json.loads(trained_on.read_text()) if trained_on.is_file() else None
    return {
        "model": repo_path(model),
        "seconds": round(_seconds(model), 1),
        "trained_on": on,
        "stopped": note,
        **vpt,
    }


def _evaluation(model: pathlib.Path) -> pathlib.Path:
    """Where `keyvision evaluate` writes a model's evaluation."""
    return model.parent / f"{model.name}-evaluate"


def _evaluate_arguments(model: pathlib.Path, data: pathlib.Path) -> list:
    """`keyvision evaluate` of a trained model: of its last finished stage where it stopped early."""
    note = _stopped(model)
    stage = ["--stage", note["evaluated_stage"]] if note else []
    return ["evaluate", "--model", model, *stage, "--data", data, "--out", _evaluation(model), "--overwrite"]


def _ready(training: tuple) -> bool:
    """Whether the autoencoder stage that a training starts from (if any) is over."""
    source = training[3]
    return source is None or _trained(source) or (source / "model-dynamics.eqx").is_file()


def _train_concurrently(trainings: list, jobs: int, device: str) -> None:
    """Run `trainings` (model, data, options, the model whose autoencoder it starts from or None) as up
    to `jobs` `keyvision train` processes at once, each writing `<model>-train.log`; a training that
    starts from another's autoencoder waits until that stage is over. Each trained model's `keyvision
    evaluate` runs in the same pool (`<model>-evaluate.log`), before the trainings still waiting (so
    that a call cut short leaves every model it trained evaluated); one that fails is left to the
    table's own evaluation, which reports its error. A training that fails with no stage finished
    interrupts the others (each keeps its checkpoints) and ends the call."""
    from cldyn._cli._common import INTERRUPTED  # a training's exit status when stopped by SIGINT

    pending = [t for t in trainings if not _trained(t[0])]
    # trained, not evaluated yet: (model, data)
    evaluations = [(t[0], t[1]) for t in trainings if _trained(t[0]) and not _finished(t[0])]
    running: dict = {}  # (model, "train" or "evaluate") -> (process, log, started)

    # on a GPU each JAX process would ask for 75% of its memory at its start, and the second would fail:
    # each takes what it needs instead, unless the caller said otherwise
    environment = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false", **os.environ}

    def start(model: pathlib.Path, kind: str, arguments: list) -> None:
        log = model.parent / f"{model.name}-{kind}.log"
        command = [sys.executable, "-m", "keyvision", *(str(a) for a in arguments)]
        with log.open("w") as stream:
            process = subprocess.Popen(command, stdout=stream, stderr=subprocess.STDOUT, env=environment)
        running[model, kind] = (process, log, time.perf_counter())
        print(f"{kind} {model} ({len(running)} at once; log {log})", flush=True)

    try:
        while pending or evaluations or running:
            while evaluations and len(running) < jobs:
                model, data = evaluations.pop(0)
                start(model, "evaluate", _evaluate_arguments(model, data))
            for training in [t for t in pending if _ready(t)][: jobs - len(running)]:
                pending.remove(training)
                start(training[0], "train", _train_arguments(*training[:3]))
            for (model, kind), (process, log, started) in list(running.items()):
                if process.poll() is None:
                    continue
                del running[model, kind]
                seconds, status = time.perf_counter() - started, process.returncode
                if kind == "evaluate":
                    said = "evaluated" if status == 0 else f"failed to evaluate (status {status}; see {log})"
                    print(f"{said} {model} in {seconds / 60:.1f} min", flush=True)
                    continue
                if status in (INTERRUPTED, -signal.SIGINT):  # not a result: stop, resumable
                    raise SystemExit(
                        f"vision_table: {model} was interrupted (its checkpoints kept; the same "
                        "command resumes it)"
                    )
                if status != 0 and not _record_stop(model, log.read_text(), f"status {status}"):
                    raise SystemExit(f"keyvision train failed for {model} (status {status}): see {log}")
                _record_device(model, device, jobs, seconds)
                print(f"trained {model} in {seconds / 60:.1f} min", flush=True)
                evaluations.append((model, next(t[1] for t in trainings if t[0] == model)))
            if pending and not running and not evaluations and not any(_ready(t) for t in pending):
                raise SystemExit("vision_table: trainings wait for an autoencoder that no training makes")
            time.sleep(1)
    finally:
        for process, _, _ in running.values():
            process.send_signal(signal.SIGINT)  # `keyvision train` checkpoints and stops; evaluate stops
        for process, _, _ in running.values():
            process.wait()


def _summary(evaluations: list[dict]) -> dict:
    per_run = np.concatenate([np.asarray(e["vpt_per_run"]) for e in evaluations])
    return {
        "mean": float(per_run.mean()),
        "std": float(per_run.std()),
        "median": float(np.median(per_run)),
        "seed_means": [e["vpt"]["mean"] for e in evaluations],
        "stopped": [{**e["stopped"], "model": e["model"]} for e in evaluations if e.get("stopped")],
        "runs": evaluations[0]["runs"],
        "seconds": [e["seconds"] for e in evaluations],
        "trained_on": [e.get("trained_on") for e in evaluations],
        "mse_per_run": np.concatenate([errors(e["mse_per_run"]) for e in evaluations]).tolist(),
        "threshold": evaluations[0]["threshold"],
        "dt": evaluations[0]["dt"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["pendulum", "cartpole", "acrobot"])
    parser.add_argument(
        "--out", default=None, help="the models (default: runs/bench-vision-table, -augmented with --augment)"
    )
    parser.add_argument("--runs", type=int, default=500)
    parser.add_argument(
        "--seeds", type=int, default=1, help="KeyCLD's seeds (3 in the issue, where time allows)"
    )
    parser.add_argument("--ablation-seeds", type=int, default=1, help="seeds of each ablation")
    parser.add_argument(
        "--models",
        nargs="+",
        choices=["KeyCLD", *VARIANTS],
        default=["KeyCLD", *VARIANTS],
        help="the rows to train, in this order (default: all); KeyCLD's first seed is trained first "
        "whenever one of them starts from its autoencoder (all but FC)",
    )
    parser.add_argument(
        "--report",
        action="store_true",
        help="train nothing: the table and figures of the models already finished",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="trainings at once, each its own process (several share a GPU well; 2 on 2 CPU cores)",
    )
    parser.add_argument(
        "--loop",
        choices=("host", "compiled"),
        default="host",
        help="`keyvision train --loop`: how the stages of images run their steps (a setting of the "
        "machine, like --jobs: tables of either loop join)",
    )
    parser.add_argument(
        "--pair-autoencoders",
        action="store_true",
        help="start each seed s of an ablation of the dynamics from the autoencoder of KeyCLD's seed s "
        "(seed 0's where KeyCLD has fewer seeds), not all from seed 0's",
    )
    parser.add_argument(
        "--results",
        default=None,
        help="the name of the files written to benchmarks/results (default: vision_table, "
        "vision_table_augmented with --augment); another keeps a table trained elsewhere apart",
    )
    add_recipe(parser, rounds=1)
    args = parser.parse_args()
    if args.jobs < 1:
        parser.error(f"--jobs {args.jobs}: give at least 1")
    # `kill -INT` stops the table and its trainings, checkpointed (`keyvision train` stops so on
    # KeyboardInterrupt), even where a shell without job control (`nohup ... &` in a script) started
    # it ignoring SIGINT, which its trainings would inherit: a caught signal is reset to its default in
    # a new program, an ignored one stays ignored
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if args.out is None:
        args.out = str(ROOT / "runs" / ("bench-vision-table" + ("-augmented" if args.augment else "")))
    results = _name(args)
    import jax

    started = time.perf_counter()
    call = {
        "command": " ".join(["python", *sys.argv]),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    first = jax.devices()[0]
    device = str(first) if first.platform == "cpu" else f"{first} ({first.device_kind})"
    plans = {}
    for scene in args.scenes:
        out = pathlib.Path(args.out) / scene
        if not (out / "data" / "frames.npz").is_file():
            if args.report:
                continue
            _cli("render", "--scene", f"keycld/{scene}", "--out", out / "data", "--runs", args.runs)
        plans[scene] = _plan(args, out)
    if args.jobs > 1 and not args.report:
        trainings = [training for plan in plans.values() for row in plan.values() for training in row]
        _train_concurrently(trainings, args.jobs, device)
    scenes = {}
    for scene, plan in plans.items():
        data = pathlib.Path(args.out) / scene / "data"
        rows, models = {}, {}
        for name, row in plan.items():
            runs = [
                _train_and_evaluate(model, data, options, device)
                for model, _, options, _ in row
                if not args.report or _finished(model)
            ]
            if runs:
                rows[name], models[name] = _summary(runs), row[0][0]
        if not rows:
            continue
        plot_mse(RESULTS / f"{results}_mse_{scene}.png", scene, rows)
        stages = {name: (m, (_stopped(m) or {}).get("evaluated_stage")) for name, m in models.items()}
        plot_frames(RESULTS / f"{results}_frames_{scene}.png", data, stages)
        scenes[scene] = rows
        # written after every scene: a call cut short leaves the table of the scenes it finished
        _write(scenes, args, device, {**call, "seconds": round(time.perf_counter() - started, 1)})


def _plan(args, out: pathlib.Path) -> dict:
    """A scene's rows, in training order: name -> [(model directory, data directory, `keyvision train`
    options, the model whose autoencoder it starts from or None), one per seed]."""
    recipe = recipe_options(args)
    plan = {
        "KeyCLD": ([], False, args.seeds),
        **{name: (*variant, args.ablation_seeds) for name, variant in VARIANTS.items()},
    }
    # one initialisation where there is no autoencoder stage to choose: a shared one (so for the
    # dynamics without constraints too, which would have nothing to choose by)
    single = recipe_options(argparse.Namespace(**{**vars(args), "candidates": 1}))
    rows = {}
    for name in ["KeyCLD", *(name for name in args.models if name != "KeyCLD")]:
        options, shared, seeds = plan[name]
        if name == "KeyCLD" and "KeyCLD" not in args.models:
            # its first seed, from whose autoencoder the ablations but FC start; none where only FC,
            # which trains its own networks, is asked for
            needed = any(VARIANTS[other][1] for other in args.models if other != "KeyCLD")
            seeds = min(seeds, 1) if needed else 0
        slug = "keycld" if name == "KeyCLD" else name.lower().replace(" ", "-")
        rows[name] = []
        for s in range(seeds):
            paired = args.pair_autoencoders and s < len(rows["KeyCLD"])
            source = out / f"keycld-{s if paired else 0}" if shared else None
            share = ["--networks-from", source] if shared else []
            loop = ["--loop", args.loop] if args.loop != "host" else []
            options_s = [*(single if shared else recipe), *options, *share, *loop, "--seed", s]
            rows[name].append((out / f"{slug}-{s}", out / "data", options_s, source))
    return rows


def _name(args) -> str:
    """The results' name: `--results`, else vision_table, or vision_table_augmented for the table trained
    with `--augment`."""
    if args.results:
        return args.results
    return "vision_table_augmented" if args.augment else "vision_table"


def _finished(model: pathlib.Path) -> bool:
    return _trained(model) and (_evaluation(model) / "vpt.json").is_file()


def _seed_counts(scenes: dict) -> str:
    """How many seeds each row holds, scene by scene ("KeyCLD 3 (acrobot), 1 (pendulum, cartpole); ...")."""
    said = []
    for name in ["KeyCLD", *VARIANTS]:
        counts: dict[int, list[str]] = {}
        for scene, rows in scenes.items():
            if name in rows:
                counts.setdefault(len(rows[name]["seed_means"]), []).append(scene)
        if len(counts) == 1:  # the same number on every scene that has the row
            said.append(f"{name} {next(iter(counts))}")
        elif counts:
            parts = [f"{n} ({', '.join(where)})" for n, where in sorted(counts.items(), reverse=True)]
            said.append(f"{name} {', '.join(parts)}")
    return "; ".join(said)


def _seed_of(stop: dict) -> str:
    """ ", seed N" for a stopped training whose model directory is known (`<slug>-<N>`), else ""."""
    seed = pathlib.Path(stop.get("model", "")).name.rpartition("-")[2]
    return f", seed {seed}" if seed.isdigit() else ""


def _earlier(args, device: str, recipe: dict, call: dict, scenes: dict) -> tuple[dict, list]:
    """The scenes of the table already written under this name that this call does not redo, with the
    calls that made them: a table built over several calls (a scene per call on a device lent for a
    while) keeps them, where the recipe (how many trainings ran at once and the step loop aside) and
    the device agree. Another recipe's or device's table is replaced, as it was before there were
    several calls."""
    path = RESULTS / f"{_name(args)}.json"
    if not path.is_file():
        return {}, []
    try:
        earlier = json.loads(path.read_text())
    except json.JSONDecodeError:  # a file cut short: nothing to keep
        return {}, []

    def same(r: dict) -> dict:
        return {k: v for k, v in r.items() if k not in ("jobs", "loop")}

    if same(earlier.get("recipe", {})) != same(recipe) or earlier.get("device") != device:
        return {}, []
    kept = {s: rows for s, rows in earlier["scenes"].items() if s not in scenes}
    calls = earlier.get("calls") or [  # a table written before calls were recorded: one call
        {"started": earlier["machine"]["date"], "seconds": earlier["seconds_this_call"], "scenes": [*kept]}
    ]
    others = [c for c in calls if c["started"] != call["started"]]  # this call's earlier scenes are redone
    others = [{**c, "scenes": [s for s in c["scenes"] if s in kept]} for c in others]
    return kept, [c for c in others if c["scenes"]]


def _write(scenes: dict, args, device: str, call: dict) -> None:
    """benchmarks/results/vision_table{,_augmented}.{json,md} (or `--results`) from the rows of the
    scenes done, and of those an earlier call of the same recipe on the same device wrote there."""
    recipe = {
        name: getattr(args, name)
        for name in vars(args)
        if name not in ("scenes", "out", "report", "models", "results")
    }
    kept, calls = _earlier(args, device, recipe, call, scenes)
    scenes = {**kept, **scenes}
    calls = [*calls, {**call, "scenes": [s for s in scenes if s not in kept]}]
    result = {
        "machine": machine(),
        "device": device,
        "recipe": recipe,
        "seconds_this_call": call["seconds"],
        "calls": calls,
        "scenes": {
            s: {n: {k: v for k, v in r.items() if k != "mse_per_run"} for n, r in rows.items()}
            for s, rows in scenes.items()
        },
    }
    names = ["KeyCLD", *VARIANTS]
    first = next(iter(scenes.values()))
    runs = first["KeyCLD"]["runs"] if "KeyCLD" in first else next(iter(first.values()))["runs"]
    lines = [
        "# The paper's ablation study from images (Table 1)"
        + (", every estimator trained with `--augment`" if args.augment else ""),
        "",
        f"VPT over the {runs} validation runs, mean +- std (median); the paper's value in brackets; - where "
        f"not run yet. Seeds: {_seed_counts(scenes)}; a row of several seeds pools their runs, and its "
        "seeds' own means follow it. "
        f"Recipe: `{' '.join(str(o) for o in recipe_options(args))}` on {device} "
        f"({result['machine']['cpus']} CPUs); training time per model in the second table (an ablation "
        "that starts from KeyCLD's autoencoder stage counts that stage's time).",
        "",
        "| model | " + " | ".join(scenes) + " |",
        "| --- |" + " --- |" * len(scenes),
    ]
    for name in names:
        cells = []
        for scene, rows in scenes.items():
            paper = PAPER.get(name, {}).get(scene)
            row = rows.get(name)
            cell = "-" if row is None else f"{row['mean']:.2f} +- {row['std']:.2f} ({row['median']:.2f})"
            if row is not None and row.get("stopped"):  # a training that diverged: see the notes
                cell += " *"
            if row is not None and len(row["seed_means"]) > 1:
                cell += "; seeds " + " / ".join(f"{m:.2f}" for m in row["seed_means"])
            cells.append(cell + ("" if paper is None else f" [{paper:.2f}]"))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "| model | " + " | ".join(scenes) + " |", "| --- |" + " --- |" * len(scenes)]
    elsewhere = set()  # (device, trainings at once) of the models trained on an accelerator
    for name in names:
        cells = []
        for rows in scenes.values():
            if name not in rows:
                cells.append("-")
                continue
            said = []
            times = rows[name]["seconds"]
            for took, on in zip(times, rows[name].get("trained_on") or [None] * len(times)):
                if on and not on["device"].lower().startswith("cpu"):
                    elsewhere.add((on["device"], on["concurrent_trainings"]))
                    said.append(f"{on['wall_seconds'] / 60:.1f} min †")
                else:
                    said.append(f"{took / 60:.0f} min")
            cells.append(" / ".join(said))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if elsewhere:
        kinds: dict[str, set] = {}
        for device, jobs in elsewhere:
            kinds.setdefault(device, set()).add(str(jobs))
        where = "; ".join(f"{d}, {' or '.join(sorted(j))} trainings at once" for d, j in kinds.items())
        lines += [
            "",
            f"† Trained on {where}, each its own `keyvision train` process: the wall time of that "
            "process, compilation included, while the others shared the device; an ablation that "
            "starts from KeyCLD's autoencoder does not count that stage here.",
        ]
    stops = [
        f"- {name}, {scene}{_seed_of(stop)}: {stop['error']}; the model after its "
        f"`{stop['evaluated_stage']}` stage is evaluated in its place."
        for scene, rows in scenes.items()
        for name, row in rows.items()
        for stop in row.get("stopped") or []
    ]
    if stops:
        lines += ["", "\\* The training stopped before its end:", "", *stops]
    if len(calls) > 1:
        lines += ["", f"Built over {len(calls)} calls of the command, on {device}:", ""]
        lines += [
            f"- {', '.join(c['scenes'])}: {c['seconds']:.0f} s from {c['started']}"
            + (f", `{c['command']}`" if c.get("command") else "")
            for c in calls
        ]
    write(_name(args), result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
