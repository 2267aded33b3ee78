"""Missing physics found from camera frames: effects injected into the KeyCLD scenes, rendered, and looked
for with `keyvision.identify` and the models learnt from images (MuJoCo as reality).

Each case renders runs of the paper's protocol (`--runs`, the last `--validation-runs` held out) from the
scene with one effect injected (`cldyn.mujoco.modify_scene`), encodes them with the scene's learnt model
and runs `keyvision.identify`: the detected effect and joint, its value in MuJoCo's units against the
truth, and the held-out VPT and image MSE before and after. Negative controls: the same scenes with
nothing injected, `--seeds` seeds each.

Writes benchmarks/results/vision_identify.{json,md} (cases and negative controls not run keep their
previous rows); prints the JSON.

    python benchmarks/vision_identify.py                       # every case
    python benchmarks/vision_identify.py --scenes pendulum     # one scene's cases
    python benchmarks/vision_identify.py --scenes pendulum --attributes frictionloss --seeds 0
    python benchmarks/vision_identify.py --scenes pendulum --attributes damping --seeds 0 --refine-steps 300
    python benchmarks/vision_identify.py --scenes acrobot --attributes stock --seeds 0  # the stock acrobot
    python benchmarks/vision_identify.py --scenes acrobot --attributes stock --frames 300   # 3 s runs
    python benchmarks/vision_identify.py --scenes acrobot --attributes stock --frames 300 --seeds 0 \
        --model acrobot=benchmarks/results/vision_models/acrobot-camera4   # another model, its camera
    python benchmarks/vision_identify.py --scenes acrobot --attributes stock --frames 300 --seeds 0 \
        --model acrobot=benchmarks/results/vision_models/acrobot-structured --stock-seeds 7 1 2 --oracle

The stock cases render dm_control's own physics under KeyCLD's camera and look
(`cldyn.mujoco.keycld_scene(name, physics="stock")`); the model's inputs take the frames' controls by
actuator name (`keyvision.identify(inputs=)`: the stock acrobot drives the elbow only). Frames come
through the camera each model was trained on (its `keyvision.json`'s `data.supersample`); a row whose
model is not the scene's committed one names it.

`--oracle` runs no identification: for the selected damping rows already written (a row of the same
runs, model and `--add-balance`), it adds the true damping to the row's learnt model and scores it on
the row's held-out runs as identify's own additions are scored. What the image criteria give with the
exact value separates an error of the identification from a limit of the learnt model.
"""

import argparse
import json
import os
import pathlib
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, VISION_MODELS, machine, repo_path, write  # noqa: E402

MODELS = VISION_MODELS
STOCK_SEED = 7  # the seed of the cases' runs (the stock cases also run at --stock-seeds)
PAPER_FRAMES = 50  # frames per run in the paper's protocol; rows of other lengths say theirs
# (scene, joint, MJCF attribute, value, the effect identify reports)
CASES = [
    ("pendulum", "hinge", "damping", 0.1, "joint_damping"),
    ("pendulum", "hinge", "armature", 0.05, "joint_armature"),
    ("pendulum", "hinge", "frictionloss", 0.3, "joint_coulomb"),
    ("cartpole", "slider", "damping", 1.0, "joint_damping"),
    ("cartpole", "slider", "damping", 3.0, "joint_damping"),
    ("cartpole", "hinge_1", "damping", 0.01, "joint_damping"),
    ("cartpole", "hinge_1", "damping", 0.03, "joint_damping"),
    ("cartpole", "hinge_1", "damping", 0.1, "joint_damping"),
    ("acrobot", "elbow", "damping", 0.1, "joint_damping"),
    ("acrobot", "elbow", "damping", 0.3, "joint_damping"),
    ("acrobot", "elbow", "damping", 1.0, "joint_damping"),
    ("acrobot", "shoulder", "damping", 0.1, "joint_damping"),
    ("acrobot", "shoulder", "damping", 0.3, "joint_damping"),
    ("acrobot", "shoulder", "damping", 1.0, "joint_damping"),
]
# dm_control's own physics under KeyCLD's camera and look (`keycld_scene(physics="stock")`): effects
# nobody injected by hand. scene -> (what the stock scene has that KeyCLD's lacks, effect, joint -> value)
STOCK = {
    "acrobot": (
        "joint damping 0.05, the elbow's motor only",
        "joint_damping",
        {"shoulder": 0.05, "elbow": 0.05},
    ),
}


def _mse(images: dict) -> str:
    """An image MSE for the table; none where some runs' predictions failed."""
    return "failed" if images["mse"] is None else f"{images['mse']:.2e}"


def _mse_head(images: dict, frames: int = PAPER_FRAMES) -> str:
    """The image MSE over the first `frames` frames of the held-out runs (the paper's horizon)."""
    curve = images.get("mse_over_time")
    return (
        "failed" if images["mse"] is None or not curve else f"{sum(curve[:frames]) / len(curve[:frames]):.2e}"
    )


def _rendered(scene: str, joints: dict | None, seed: int, length: int, model_dir, args, stock: bool):
    """The scene's model and the runs of a case: `(model, spec, frames, inputs)`, the frames rendered
    (or loaded from the cache) through the camera the model was trained on (MuJoCo's render, or one
    averaging samples), `inputs` the actuators of the scene it learnt from (the frames' controls are
    placed by name)."""
    import cldyn.mujoco
    import keyvision
    from keyvision._files import trained_supersample

    source = f"keycld/{scene}" + (":stock" if stock else "")
    xml = cldyn.mujoco.modify_scene(source, joints=joints) if joints else source
    model, spec = keyvision.load_model(model_dir)
    protocol = keyvision.RenderProtocol(
        runs=args.runs,
        validation_runs=args.validation_runs,
        frames=length,
        supersample=trained_supersample(spec),
    )
    frames = keyvision.render(xml, protocol=protocol, seed=seed, workers=1)
    return model, spec, frames, keyvision.scene_actuators(spec["data"]["scene"])


def _case(scene: str, joints: dict | None, seed: int, args, *, stock: bool = False) -> dict:
    import jax

    import keyvision
    from keyvision._files import trained_supersample

    model, spec, frames, inputs = _rendered(scene, joints, seed, args.frames, args.models[scene], args, stock)
    supersample = trained_supersample(spec)
    refine = None
    if args.refine_steps and (joints or stock):
        from keyvision._identify import joint_stage

        refine = joint_stage(spec.get("schedule") or {}, args.refine_steps)
    # what a row is kept by, refused or not: its model, its runs' length and its camera
    row = {"model": repo_path(args.models[scene]), "frames": args.frames, "supersample": supersample}
    if args.add_balance:
        row["add_balance"] = True
    started = time.perf_counter()
    try:
        result = keyvision.identify(
            model, frames, inputs=inputs, refine=refine, seed=seed, add_balance=args.add_balance
        )
    except ValueError as error:  # e.g. keypoints that break the constraints: reported, not fatal
        return {
            **row,
            "outcome": f"refused: {error}",
            "effects": [],
            "seconds": time.perf_counter() - started,
        }
    finally:
        jax.clear_caches()
    report = result.identification
    return {
        **row,
        "outcome": report.outcome,
        "effects": list(result.effects),
        "adequacy": list(report.adequacy.problems) if report.adequacy is not None else [],
        "warnings": list(report.warnings),
        "rollout_1s": [report.before.rollout_rmse_1s, report.after.rollout_rmse_1s],
        "images": result.images,
        "refine_steps": refine.joint_steps if refine is not None else 0,
        "joules_per_unit": result.joules_per_unit,
        "energy_spread": result.energy_spread,
        "balance": list(result.balance),
        # keyvision.identify smooths the balance's velocities in the scene's joint coordinates
        **({"balance_smoothing": "joints"} if result.balance else {}),
        "seconds": round(time.perf_counter() - started, 1),
    }


def _is_stock(row: dict) -> bool:
    """Whether the row is a stock-physics case (dm_control's own physics, nothing injected)."""
    return row["attribute"].startswith("stock physics")


def _truth(row: dict) -> dict[str, float]:
    """The true viscous damping of a row per joint (MuJoCo's units); empty where the row's effect is
    not a damping."""
    if _is_stock(row):
        _, effect, truth = STOCK[row["scene"]]
        return dict(truth) if effect == "joint_damping" else {}
    return {row["joint"]: row["truth"]} if row["attribute"] == "damping" else {}


def _oracle(row: dict, args) -> dict:
    """The row's learnt model with the true damping added at every joint, scored on the row's held-out
    runs as `keyvision.identify` scores its additions (VPT, image MSE, before and after). The true value
    goes to the model's units by the row's own conversion: the energy balance's value over its value in
    the model's units, at each joint."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import cldyn
    import keyvision
    from cldyn._identify.base import add_dissipation
    from keyvision._controls import _place_controls
    from keyvision._identify import _image_errors

    truth = _truth(row)
    scale = {b["where"]: b["value"] / b["value_model"] for b in row.get("balance", [])}
    if not truth or not set(truth) <= set(scale):
        raise SystemExit(f"--oracle: the row {row['scene']}, {row['attribute']} has no damping or no balance")
    stock = _is_stock(row)
    joints = None if stock else {row["joint"]: {"damping": row["truth"]}}
    seed = row.get("seed", STOCK_SEED)
    model, _, frames, inputs = _rendered(
        row["scene"], joints, seed, _frames(row), ROOT / _model(row), args, stock
    )
    frames = _place_controls(frames, inputs, model.dynamics.num_inputs)
    measured, held_out = frames.split()
    dynamics = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, model.dynamics)
    x = np.asarray(keyvision.encode_sequences(model, keyvision.ImageSequences.from_frames(measured)).x, float)
    structure = keyvision.joint_structure(dynamics.constraint, x, list(frames.info.get("joint_names", [])))
    values = {joint: value / scale[joint] for joint, value in truth.items()}
    damping = cldyn.JointDamping(
        [structure.coordinates[joint] for joint in values], jnp.asarray(list(values.values()), jnp.float64)
    )
    oracle = keyvision.KeyCLD(model.estimator, add_dissipation(dynamics, damping), model.renderer)
    images = _image_errors(model, oracle, held_out)
    jax.clear_caches()

    def head(record):
        return float(np.mean(record["mse_over_time"][:PAPER_FRAMES]))

    return {
        "values": truth,
        "values_model": values,
        "vpt": [images[k]["vpt"]["mean"] for k in ("before", "after")],
        "mse": [images[k]["mse"] for k in ("before", "after")],
        "mse_head": [head(images[k]) for k in ("before", "after")],
    }


def _balance(row: dict) -> str:
    """The energy balance's damping per joint, for the table."""
    return (
        ", ".join(
            f"{b['where']} {b['value']:.3g} [{b['ci'][0]:.3g}, {b['ci'][1]:.3g}]"
            + ("*" if b["detected"] else "")
            for b in row.get("balance", [])
        )
        or "-"
    )


def _frames(row: dict) -> int:
    return row.get("frames", PAPER_FRAMES)  # rows from before --frames: the paper's


def _length(row: dict) -> str:
    """How a row's runs and model differ from the paper's and the committed ones, for its label ("" for
    the paper's length and the scene's committed model)."""
    label = "" if _frames(row) == PAPER_FRAMES else f", runs of {_frames(row)} frames"
    if _model(row) != repo_path(MODELS[row["scene"]]):
        label += f", model {pathlib.Path(_model(row)).name}"
    if row.get("supersample", 1) > 1:
        label += f", camera {row['supersample']} x {row['supersample']}"
    if row.get("add_balance"):
        label += ", the balance's damping added"
    if "attribute" in row and row.get("seed", STOCK_SEED) != STOCK_SEED:  # a case's runs of another seed
        label += f", seed {row['seed']}"
    return label


def _selected(row: dict, args) -> bool:
    """Whether `args` select `row`: its scene, runs' length, model and options, and its case."""
    scene = row["scene"]
    if scene not in args.scenes or _frames(row) != args.frames:
        return False
    if _model(row) != repo_path(args.models[scene]) or row.get("add_balance", False) != args.add_balance:
        return False
    if _is_stock(row):
        chosen = args.stock and (not args.attributes or "stock" in args.attributes)
        return chosen and row.get("seed", STOCK_SEED) in args.stock_seeds
    if args.attributes and row["attribute"] not in args.attributes:
        return False
    return row.get("seed", STOCK_SEED) == STOCK_SEED and (
        not args.values or f"{row['joint']}={row['truth']:g}" in args.values
    )


def _model(row: dict) -> str:
    """The row's model (rows written before it was stored: the scene's committed model)."""
    return row.get("model") or repo_path(MODELS[row["scene"]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="SCENE=DIR",
        help="a scene's model learnt from images (by default the committed ones, _common.VISION_MODELS)",
    )
    parser.add_argument("--no-stock", dest="stock", action="store_false", help="skip the stock-physics cases")
    parser.add_argument("--runs", type=int, default=60)
    parser.add_argument("--validation-runs", type=int, default=10)
    parser.add_argument(
        "--frames",
        type=int,
        default=PAPER_FRAMES,
        help="frames per run (the paper's 50 by default; longer runs for effects too slow to show in 50)",
    )
    parser.add_argument("--seeds", type=int, default=5, help="seeds of the effect-free data per scene")
    parser.add_argument(
        "--refine-steps",
        type=int,
        default=0,
        help="then train each case's model jointly with the image losses (keyvision.identify(refine=)) "
        "this many steps of its joint stage, and score it beside",
    )
    parser.add_argument(
        "--stock-seeds",
        type=int,
        nargs="+",
        default=[STOCK_SEED],
        help=f"seeds of the stock-physics cases' runs ({STOCK_SEED} by default, as every case's)",
    )
    parser.add_argument(
        "--add-balance",
        action="store_true",
        help="add the energy balance's damping to the model where identify detected none "
        "(keyvision.identify(add_balance=True)); such rows are kept beside the others",
    )
    parser.add_argument(
        "--oracle",
        action="store_true",
        help="identify nothing: add the true damping to the selected rows' models and score them (the "
        "rows must exist; see above)",
    )
    parser.add_argument(
        "--attributes", nargs="+", help="only the cases that inject these MJCF attributes (all by default)"
    )
    parser.add_argument(
        "--values",
        nargs="+",
        metavar="JOINT=VALUE",
        help="only the injected cases of these joints and values, e.g. elbow=0.3 (all by default)",
    )
    args = parser.parse_args()
    args.models = {**MODELS, **dict(item.split("=", 1) for item in args.model)}
    import jax

    jax.config.update("jax_enable_x64", True)
    rows, negatives = [], []
    for scene, joint, attribute, value, effect in CASES if not args.oracle else ():
        if scene not in args.scenes or (args.attributes and attribute not in args.attributes):
            continue
        if args.values and f"{joint}={value:g}" not in args.values:
            continue
        found = _case(scene, {joint: {attribute: value}}, STOCK_SEED, args)
        top = found["effects"][0] if found["effects"] else None
        right = top is not None and (top["name"], top["where"]) == (effect, joint)
        rows.append(
            {
                "scene": scene,
                "joint": joint,
                "attribute": attribute,
                "truth": value,
                "effect": effect,
                "right": right,
                "error": None if not right or top["value"] is None else top["value"] / value - 1,
                **found,
            }
        )
    for scene, (differs, effect, truth) in STOCK.items() if not args.oracle else ():
        if scene not in args.scenes or not args.stock or (args.attributes and "stock" not in args.attributes):
            continue
        for seed in args.stock_seeds:
            found = _case(scene, None, seed, args, stock=True)
            values = {e["where"]: e["value"] for e in found["effects"] if e["name"] == effect}
            errors = {joint: values[joint] / value - 1 for joint, value in truth.items() if values.get(joint)}
            right = len(found["effects"]) == len(truth) and len(errors) == len(truth)
            worst = max(errors.values(), key=abs) if right else None
            rows.append(
                {
                    "scene": scene,
                    "joint": ", ".join(truth),
                    "attribute": f"stock physics ({differs})",
                    "truth": max(truth.values()),
                    "effect": effect,
                    "right": right,
                    "error": worst,
                    "errors": errors,
                    **({} if seed == STOCK_SEED else {"seed": seed}),
                    **found,
                }
            )
    for scene in args.scenes if not args.oracle else ():
        for seed in range(args.seeds):
            negatives.append({"scene": scene, "seed": seed, **_case(scene, None, seed, args)})
    previous = RESULTS / "vision_identify.json"
    case = lambda r: (  # noqa: E731
        r["scene"],
        r["joint"],
        r["attribute"],
        r["truth"],
        _frames(r),
        _model(r),
        r.get("add_balance", False),
        r.get("seed", STOCK_SEED),
    )
    if previous.is_file():  # the cases and negative controls not run this time keep their previous rows
        earlier = json.loads(previous.read_text())
        negative = lambda n: (n["scene"], n["seed"], _frames(n), _model(n), n.get("add_balance", False))
        ran = {case(r) for r in rows} | {negative(n) for n in negatives}
        rows = [r for r in earlier.get("cases", []) if case(r) not in ran] + rows
        negatives = [n for n in earlier.get("negatives", []) if negative(n) not in ran] + negatives
    if args.oracle:
        chosen = [r for r in rows if _selected(r, args) and _truth(r) and r.get("balance")]
        if not chosen:
            raise SystemExit("--oracle: no damping row of these runs, model and options was written")
        for row in chosen:
            row["oracle"] = _oracle(row, args)
            print(_length(row).lstrip(", ") or row["scene"], row["oracle"], file=sys.stderr, flush=True)
    order = list(MODELS)
    keys = [c[:4] for c in CASES]
    rows.sort(
        key=lambda r: (
            order.index(r["scene"]),
            keys.index(case(r)[:4]) if case(r)[:4] in keys else len(keys),
            _frames(r),
            _model(r),
        )
    )
    negatives.sort(key=lambda n: (order.index(n["scene"]), n["seed"], _frames(n), _model(n)))
    scenes = [scene for scene in order if any(n["scene"] == scene for n in negatives)]
    result = {
        "machine": machine(),
        "runs": args.runs,
        "validation_runs": args.validation_runs,
        "cases": rows,
        "negatives": negatives,
    }
    lines = [
        "# Missing physics from camera frames (keyvision identify)",
        "",
        f"{args.runs} runs of the paper's protocol per case ({args.validation_runs} held out for the image "
        "errors; 50 frames each unless the row says more: longer runs for effects too slow to show in "
        "0.5 s), rendered with one effect injected, identified against the scene's model learnt from images "
        "(`benchmarks/vision_identify.py`). Values in MuJoCo's units (`keyvision.identify`'s conversion).",
        "",
        "The last column is `cldyn.energy_balance` on the same keypoints and model (reported by "
        '`keyvision.identify` beside its detections; added to the model only in the rows marked "the '
        "balance's damping added\", `--add-balance`): the viscous damping each joint lacks by the balance "
        "of energy, with its 95% interval, in MuJoCo's units; `*` where the interval lies above zero (rows "
        "from before the balance have `-`).",
        "",
        "| scene | injected | outcome | found | value (error) | held-out VPT before -> after "
        "| image MSE before -> after | energy balance |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        top = row["effects"][0] if row["effects"] else None
        found = ", ".join(f"{e['name']}[{e['where']}]" for e in row["effects"]) or "-"
        value = "-" if top is None or top["value"] is None else f"{top['value']:.4g}"
        if row["error"] is not None:
            value += f" ({row['error']:+.1%})"
        if len(row["effects"]) > 1:  # every effect found, with its error where the truth is known
            errors = row.get("errors", {})
            value = ", ".join(
                f"{e['value']:.4g}" + (f" ({errors[e['where']]:+.1%})" if e["where"] in errors else "")
                for e in row["effects"]
                if e["value"] is not None
            )
        images = row.get("images") or {}
        vpt = mse = "-"
        if images:
            vpt = f"{images['before']['vpt']['mean']:.3f} -> {images['after']['vpt']['mean']:.3f}"
            mse = f"{_mse(images['before'])} -> {_mse(images['after'])}"
            if _frames(row) > PAPER_FRAMES:  # and over the paper's horizon
                head = f"{_mse_head(images['before'])} -> {_mse_head(images['after'])}"
                mse += f" (first {PAPER_FRAMES} frames {head})"
            if "refined" in images:  # then jointly with the image losses
                vpt += f" -> {images['refined']['vpt']['mean']:.3f} (image refit)"
                mse += f" -> {_mse(images['refined'])} (image refit)"
        outcome = row["outcome"] + (f" ({'; '.join(row['adequacy'])})" if row.get("adequacy") else "")
        lines.append(
            f"| {row['scene']} | {row['attribute']} {row['truth']} at {row['joint']}{_length(row)} "
            f"| {outcome} | {found} | {value} | {vpt} | {mse} | {_balance(row)} |"
        )
    # what identify names when the residual asks for an effect of the forbidden sign: the model's own error
    labels = [f"{r['scene']}, {r['attribute']} {r['truth']} at {r['joint']}{_length(r)}" for r in rows]
    labels += [f"{n['scene']}, effect-free, seed {n['seed']}{_length(n)}" for n in negatives]
    asks = [
        (f"{label} ({warning.split(':', 1)[0]})", warning.split("asks for ", 1)[1].split(": a sign", 1)[0])
        for label, row in zip(labels, rows + negatives)
        for warning in row.get("warnings", [])
        if "the residual asks for" in warning
    ]
    if asks:
        lines += [
            "",
            "Where the residual asks for an effect of the forbidden sign (in the model's units; "
            "the learnt model overstates what it stands for):",
            "",
        ]
        lines += [f"- {label}: {named}" for label, named in asks]
    # the balance's damping that `--add-balance` left out: it did not lower the held-out rollout error
    refused = [
        f"- {label}: {warning}"
        for label, row in zip(labels, rows + negatives)
        for warning in row.get("warnings", [])
        if warning.startswith(("the energy balance's", "with the energy balance's"))
    ]
    if refused:
        lines += ["", "The balance's damping that the held-out rollout test left out (`--add-balance`):"]
        lines += [""] + refused
    # the row each score belongs to (not what it added: the oracle adds the truth alone)
    oracles = [
        (label.replace(", the balance's damping added", " (the --add-balance row)"), row["oracle"])
        for label, row in zip(labels, rows)
        if "oracle" in row
    ]
    if oracles:
        lines += [
            "",
            "The learnt model with the true damping added (`--oracle`: no identification), held-out VPT and "
            f"image MSE over the first {PAPER_FRAMES} frames, before -> after:",
            "",
        ]
        lines += [
            f"- {label}: VPT {o['vpt'][0]:.3f} -> {o['vpt'][1]:.3f}, image MSE {o['mse_head'][0]:.4g} -> "
            f"{o['mse_head'][1]:.4g} ({o['mse_head'][1] / o['mse_head'][0] - 1:+.1%})"
            for label, o in oracles
        ]
    lines += ["", "Effect-free data (negative control):", ""]
    for scene in scenes:
        groups = {
            (_frames(n), _model(n), n.get("add_balance", False)) for n in negatives if n["scene"] == scene
        }
        for group in sorted(groups):
            mine = [
                n
                for n in negatives
                if n["scene"] == scene and (_frames(n), _model(n), n.get("add_balance", False)) == group
            ]
            quiet = sum(1 for n in mine if not n["effects"])
            outcomes = ", ".join(
                ", ".join(
                    f"{e['name']}[{e['where']}]"
                    + (" by the energy balance" if e.get("source") == "energy balance" else "")
                    for e in n["effects"]
                )
                or n["outcome"]
                for n in mine
            )
            length = f" ({_length(mine[0]).lstrip(', ')})" if _length(mine[0]) else ""
            balanced = [n for n in mine if "balance" in n]
            if balanced:  # the energy balance's false detections, where it ran
                clean = sum(1 for n in balanced if not any(b["detected"] for b in n["balance"]))
                outcomes += (
                    f"; the energy balance: no joint's interval above zero in {clean} of {len(balanced)}"
                )
            lines.append(f"- {scene}{length}: nothing detected in {quiet} of {len(mine)} seeds ({outcomes})")
    write("vision_identify", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
