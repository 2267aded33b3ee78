"""Learning dynamics from keypoint states: KeyCLD vs KeyCLD-NC vs NODE2 on the three KeyCLD scenes.

The state-space counterpart of the KeyCLD paper's ablation (Table 1). For each fully actuated KeyCLD
scene (pendulum, cartpole, acrobot) the data follow the paper's protocol (appendix A.6: 500 runs x 50
frames recorded with MuJoCo, the first 450 train, the last 50 validate) and every model is trained with
the same loss and budget:

- `keycld`: the paper's model, point masses (eq. 14) + MLP potential + MLP input matrix + the scene's
  constraints (figure 7);
- `keycld-coupled`: the same with a constant mass matrix `A (x) I_2` that couples keypoints
  (`cldyn.CoupledMasses`), exact for the uniform rods of the cartpole and the acrobot;
- `nc`: KeyCLD without the constraint (KeyCLD-NC);
- `node2`: the second-order neural ODE of appendix A.4.

Loss: finite-difference collocation (eq. 11-13; by default with the fourth-order stencils of
`cldyn.Collocation(order=4)`, `--order 2` for the paper's central differences) on float32, Adam
(peak 3e-3, cosine decay to 3e-5) after element-wise gradient clipping at 5, batches of 32 runs.
Evaluation in float64 on held-out runs:

- the paper's validation split (runs 450-499, 50 frames): VPT as a fraction of the sequence, the
  layout of Table 1;
- 50 further runs of 1 s (seed 1): VPT in seconds and the RMS keypoint error over 1 s as a percentage
  of the range of motion (the largest spread of any keypoint coordinate in those runs), over all runs
  and over the non-chaotic ones.

VPT threshold: 10% of the range of motion (a keypoint distance). A run is *chaotic* when the exact
dynamics (`cldyn.mujoco.from_mjcf` of the scene, which matches MuJoCo to integration accuracy) amplify
a perturbation of the initial velocity more than 10-fold relative to free drift within the 1 s
(`max_t |dx(t)| / (|dv| t) > 10`). The exact model is evaluated alongside as a reference.

Writes benchmarks/results/learning.json and learning.md, loss-curve and rollout plots (PNG), and the
fitted models under benchmarks/results/learning/<scene>-<model>/ (loadable with
`cldyn.load_fit`); with `--order 2` the same under `learning_order2*`. Prints one JSON
object.

    python benchmarks/learning.py [--steps 6000] [--systems pendulum cartpole acrobot]
"""

import argparse
import json
import os
import pathlib
import platform
import shutil
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import cldyn  # noqa: E402
import cldyn.mujoco as cm  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results"
MODELS = ("keycld", "keycld-coupled", "nc", "node2")
LABELS = {
    "keycld": "KeyCLD",
    "keycld-coupled": "KeyCLD (coupled M)",
    "nc": "KeyCLD-NC",
    "node2": "NODE2",
    "exact": "exact model (reference)",
}
SYSTEMS = ("pendulum", "cartpole", "acrobot")
VPT_FRACTION = 0.10  # VPT threshold: 10% of the range of motion
TARGET_PERCENT = 5.0  # acceptance: RMS error over 1 s <= 5% of the range of motion
CHAOS_AMPLIFICATION = 10.0
DATA_SEED, TEST_SEED, MODEL_SEED = 0, 1, 0


def _name(args) -> str:
    """`learning*` for fourth-order collocation (the default), `learning_order2*` for the paper's."""
    return "learning" if args.order == 4 else f"learning_order{args.order}"


def _cast64(model):
    return jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, model)


def _amplification(system, data: cldyn.Sequences, seconds: float) -> np.ndarray:
    """Per run: `max_t |dx(t)| / (|dv| t)` for velocity perturbations along the constraint tangent space."""
    dt = data.dt
    ts = dt * np.arange(int(round(seconds / dt)) + 1)
    eps = 1e-6

    def flow(x0, xd0, u):
        return cldyn.simulate(system, x0, xd0, ts, control=u, solver=cldyn.RK4(), dt0=dt / 2).x

    def one(x0, xd0, u):
        jac = system.constraint.jacobian(x0)
        basis = jnp.linalg.svd(jac)[2][jac.shape[0] :]
        base = flow(x0, xd0, u)
        columns = jax.vmap(lambda d: (flow(x0, xd0 + eps * d, u) - base) / eps)(basis)
        gains = jnp.linalg.svd(jnp.transpose(columns, (1, 2, 0)), compute_uv=False)[:, 0]
        return jnp.max(gains / jnp.maximum(ts, dt))

    return np.asarray(jax.jit(jax.vmap(one))(data.x[:, 1], data.xd[:, 1], data.u[:, 1]))


def _energy_drift(model, evaluation, unforced) -> float | None:
    """Median over unforced runs of `ptp(E) / ptp(V)` along the model's own rollout."""
    if not isinstance(model, cldyn.ConstrainedLagrangian) or not np.any(unforced):
        return None
    x, energy = evaluation.x[unforced], evaluation.energy[unforced]
    potential = np.asarray(jax.vmap(jax.vmap(model.potential_energy))(jnp.asarray(x)))
    ratio = np.ptp(energy, axis=1) / np.maximum(np.ptp(potential, axis=1), 1e-12)
    return float(np.median(ratio))


def _metrics(model, validation, test, rom, chaotic, unforced) -> tuple[dict, cldyn.Evaluation]:
    threshold = VPT_FRACTION * rom
    paper = cldyn.evaluate(model, validation, threshold=threshold)
    held = cldyn.evaluate(model, test, threshold=threshold)
    percent = 100 * held.error_over(1.0) / rom
    calm = ~chaotic
    return {
        "vpt_validation": float(np.mean(paper.vpt)),
        "vpt_test": float(np.mean(held.vpt)),
        "vpt_test_seconds": float(np.mean(held.vpt_seconds)),
        "error_1s_percent": float(np.mean(percent)),
        "error_1s_percent_median": float(np.median(percent)),
        "error_1s_percent_nonchaotic": float(np.mean(percent[calm])),
        "error_1s_metres_nonchaotic": float(np.mean(held.error_over(1.0)[calm])),
        "gmre": float(np.exp(np.mean(np.log(held.gmre)))),
        "energy_drift_unforced": _energy_drift(model, held, unforced),
    }, held


def _plot_losses(scene: str, histories: dict, path: pathlib.Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 4))
    for index, (name, history) in enumerate(histories.items()):
        steps = [h["step"] for h in history]
        ax.plot(steps, [h["loss"] for h in history], color=f"C{index}", lw=0.8, label=f"{LABELS[name]} train")
        val = [(h["step"], h["validation"]) for h in history if h.get("validation") is not None]
        ax.plot(*zip(*val), "o--", color=f"C{index}", ms=3, lw=1, label=f"{LABELS[name]} validation")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("collocation loss (m/s^2)^2")
    ax.set_title(f"{scene}: training curves")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_rollouts(scene: str, evaluations: dict, rom: float, chaotic, path: pathlib.Path) -> None:
    """Error over time (mean and quartiles over runs, like the paper's figure 3) and one rollout."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for index, (name, ev) in enumerate(evaluations.items()):
        color = "k" if name == "exact" else f"C{index}"
        percent = 100 * ev.error / rom
        left.plot(ev.ts, np.mean(percent, axis=0), color=color, label=LABELS[name])
        lo, hi = np.percentile(percent, [25, 75], axis=0)
        left.fill_between(ev.ts, lo, hi, color=color, alpha=0.15)
    left.axhline(100 * VPT_FRACTION, color="grey", ls="--", lw=0.8, label="VPT threshold")
    left.set_yscale("log")
    left.set_ylim(bottom=1e-5)
    left.set_xlabel("time (s)")
    left.set_ylabel("keypoint error (% of range of motion)")
    left.set_title(f"{scene}: error on 50 held-out runs")
    left.legend(fontsize=7)
    calm = np.flatnonzero(~chaotic)
    run = int(calm[0]) if calm.size else 0
    # learned models live in keypoint coordinates about the pivot; the exact model in world-plane ones
    reference = next(ev for name, ev in evaluations.items() if name != "exact")
    last = reference.x_true.shape[-1] - 2
    right.plot(
        reference.x_true[run, :, last],
        reference.x_true[run, :, last + 1],
        "k",
        lw=2.5,
        alpha=0.4,
        label="MuJoCo",
    )
    for index, (name, ev) in enumerate(evaluations.items()):
        if name != "exact":
            right.plot(
                ev.x[run, :, last], ev.x[run, :, last + 1], color=f"C{index}", lw=1, label=LABELS[name]
            )
    right.set_aspect("equal", adjustable="datalim")
    right.set_xlabel("x (m)")
    right.set_ylabel("y (m)")
    right.set_title(f"last keypoint over 1 s, held-out run {run}")
    right.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _fit(scene, name, train, validation, args, out: pathlib.Path):
    spec = {
        "kind": name,
        "size": train.size,
        "num_inputs": train.num_inputs,
        "constraint": scene if name in ("keycld", "keycld-coupled") else None,
        "width": 64 if name == "node2" else 32,
        "depth": 3 if name == "node2" else 2,
    }
    model_key = jax.random.fold_in(jax.random.key(MODEL_SEED), MODELS.index(name))
    model = cldyn.model_from_spec(spec, key=model_key)
    schedule = optax.cosine_decay_schedule(args.lr, args.steps, alpha=0.01)
    optimizer = optax.chain(optax.clip(5.0), optax.adam(schedule))
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / "fit.json").write_text(
        json.dumps(
            {
                "model": spec,
                "data": {"scene": scene, "runs": 500, "frames": 50, "noise": 0.0, "seed": DATA_SEED},
                "dt": train.dt,
                "loss": f"collocation, order {args.order}",
                "steps": args.steps,
                "batch_size": args.batch_size,
                "lr": args.lr,
                "clip": 5.0,
                "schedule": "cosine to 1%",
                "seed": MODEL_SEED,
                "validation_runs": 50,
                "dtype": "float32",
            },
            indent=1,
        )
    )
    start = time.perf_counter()
    result = cldyn.fit(
        model,
        train,
        loss=cldyn.Collocation(order=args.order),
        steps=args.steps,
        batching=cldyn.Runs(args.batch_size),
        key=jax.random.key(1000 + MODELS.index(name)),
        optimizer=optimizer,
        validation=validation,
        validate_every=max(args.steps // 20, 1),
        log_every=max(args.steps // 200, 1),
        out=out,
        checkpoint_every=args.steps,
    )
    seconds = time.perf_counter() - start
    (out / "checkpoint.eqx").unlink(missing_ok=True)  # the final model is in model.eqx
    return result, seconds


def run(args) -> dict:
    RESULTS.mkdir(parents=True, exist_ok=True)
    report = {
        "benchmark": "learning",
        "config": {
            "steps": args.steps,
            "name": _name(args),
            "batch_size": args.batch_size,
            "lr": args.lr,
            "loss": f"Collocation(order={args.order}) (eq. 11-13)",
            "optimizer": "clip(5) + adam(cosine decay from lr to lr/100)",
            "train_dtype": "float32",
            "eval_dtype": "float64",
            "data_seed": DATA_SEED,
            "test_seed": TEST_SEED,
            "model_seed": MODEL_SEED,
            "batch_keys": "jax.random.key(1000 + model index)",
            "vpt_threshold": f"{VPT_FRACTION:.0%} of range",
            "chaos": f"amplification > {CHAOS_AMPLIFICATION:g} within 1 s",
            "models": list(args.models),
            "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} "
            f"{jax.default_backend()}",
        },
        "systems": {},
    }
    for scene in args.systems:
        print(f"== {scene}", flush=True)
        data = cm.keycld_dataset(scene, seed=DATA_SEED)
        train, validation = data.split(450)
        frames = int(round(1.0 / data.dt)) + 3
        test = cm.keycld_dataset(scene, runs=50, frames=frames, seed=TEST_SEED)
        # the recordings themselves: world-plane keypoints, for the exact model
        raw_validation = cm.keycld_recording(scene, seed=DATA_SEED).split(450)[1]
        raw_test = cm.keycld_recording(scene, runs=50, frames=frames, seed=TEST_SEED)
        rom = cldyn.range_of_motion(test.x)
        exact = cm.from_mjcf(f"keycld/{scene}").system
        amplification = _amplification(exact, raw_test, 1.0)
        chaotic = amplification > CHAOS_AMPLIFICATION
        unforced = np.all(np.asarray(test.u[:, 0]) == 0, axis=1)
        entry = {
            "range_of_motion_m": rom,
            "vpt_threshold_m": VPT_FRACTION * rom,
            "chaotic_runs": int(np.sum(chaotic)),
            "amplification_max": float(np.max(amplification)),
            "models": {},
        }
        evaluations, histories = {}, {}
        metrics, evaluations["exact"] = _metrics(exact, raw_validation, raw_test, rom, chaotic, unforced)
        entry["models"]["exact"] = metrics
        total = 0.0
        for name in args.models:
            out = RESULTS / _name(args) / f"{scene}-{name}"
            result, seconds = _fit(scene, name, train, validation, args, out)
            total += seconds
            histories[name] = result.history
            metrics, evaluations[name] = _metrics(
                _cast64(result.model), validation, test, rom, chaotic, unforced
            )
            final = result.history[-1]
            metrics.update(
                {
                    "train_seconds": seconds,
                    "steps_per_second": args.steps / seconds,
                    "final_train_loss": final["loss"],
                    "final_validation_loss": final["validation"],
                }
            )
            if isinstance(result.model, cldyn.ConstrainedLagrangian):
                mass = result.model.mass
                matrix = (
                    mass.keypoint_matrix() if isinstance(mass, cldyn.CoupledMasses) else jnp.diag(mass.masses)
                )
                metrics["learned_keypoint_mass_matrix"] = np.asarray(matrix, dtype=float).round(4).tolist()
            entry["models"][name] = metrics
            print(
                f"   {name:15s} {seconds:6.1f} s  VPT(val) {metrics['vpt_validation']:.2f}  "
                f"VPT(1 s) {metrics['vpt_test_seconds']:.2f} s  "
                f"error(1 s) {metrics['error_1s_percent']:.2f}% "
                f"(non-chaotic {metrics['error_1s_percent_nonchaotic']:.2f}%)",
                flush=True,
            )
        entry["train_seconds_total"] = total
        _plot_losses(scene, histories, RESULTS / f"{_name(args)}_loss_{scene}.png")
        _plot_rollouts(scene, evaluations, rom, chaotic, RESULTS / f"{_name(args)}_rollout_{scene}.png")
        report["systems"][scene] = entry
    report["acceptance"] = _acceptance(report)
    return report


def _acceptance(report) -> dict:
    out = {}
    for scene, entry in report["systems"].items():
        models = entry["models"]
        if "keycld" not in models:
            continue
        row = {}
        for name in ("keycld", "keycld-coupled"):
            if name not in models:
                continue
            m = models[name]
            row[name] = {
                "vpt_ge_nc": all(m[k] >= models["nc"][k] for k in ("vpt_validation", "vpt_test"))
                if "nc" in models
                else None,
                "vpt_ge_node2": all(m[k] >= models["node2"][k] for k in ("vpt_validation", "vpt_test"))
                if "node2" in models
                else None,
                "error_1s_nonchaotic_le_5_percent": m["error_1s_percent_nonchaotic"] <= TARGET_PERCENT,
            }
        out[scene] = row
    return out


def _markdown(report) -> str:
    systems = list(report["systems"])
    names = [
        n
        for n in ("keycld", "keycld-coupled", "nc", "node2", "exact")
        if n in next(iter(report["systems"].values()))["models"]
    ]
    c = report["config"]
    lines = [
        "# Learning dynamics from keypoint states (benchmarks/learning.py)",
        "",
        "Data: KeyCLD protocol (A.6), 500 runs x 50 frames per scene recorded with MuJoCo "
        f"(seed {c['data_seed']}), first 450 train, last 50 validate; 50 further held-out runs of 1 s "
        f"(seed {c['test_seed']}). Training: {c['loss']}, {c['steps']} steps, batches of "
        f"{c['batch_size']} runs, {c['optimizer']}, peak lr {c['lr']}, float32. Evaluation in float64. "
        f"Machine: {c['machine']}.",
        "",
        f"VPT threshold: {VPT_FRACTION:.0%} of the range of motion (largest spread of any keypoint "
        "coordinate in the held-out runs); chaotic runs: the exact dynamics amplify an initial-velocity "
        f"perturbation more than {CHAOS_AMPLIFICATION:g}-fold within 1 s.",
        "",
        "## VPT on the paper's validation split (fraction of the 50 frames; layout of the paper's Table 1)",
        "",
        "| VPT | " + " | ".join(s.capitalize() for s in systems) + " |",
        "| --- |" + " --- |" * len(systems),
    ]
    for name in names:
        cells = [f"{report['systems'][s]['models'][name]['vpt_validation']:.2f}" for s in systems]
        lines.append(f"| {LABELS[name]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## 50 held-out runs of 1 s",
        "",
        "VPT in seconds (of 1 s); RMS keypoint error over 1 s as % of the range of motion: mean over all "
        "runs / mean over non-chaotic runs / median; geometric-mean relative error of the positions "
        "(Finzi et al.).",
        "",
        "| model | system | VPT (s) | error 1 s: all | non-chaotic | median | GMRE | energy drift (u = 0) | "
        "train time (s) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name in names:
        for s in systems:
            m = report["systems"][s]["models"][name]
            drift = "-" if m.get("energy_drift_unforced") is None else f"{m['energy_drift_unforced']:.2g}"
            train = f"{m['train_seconds']:.0f}" if "train_seconds" in m else "-"
            lines.append(
                f"| {LABELS[name]} | {s} | {m['vpt_test_seconds']:.2f} | {m['error_1s_percent']:.2f}% | "
                f"{m['error_1s_percent_nonchaotic']:.2f}% | {m['error_1s_percent_median']:.2f}% | "
                f"{m['gmre']:.2g} | {drift} | {train} |"
            )
    lines += [
        "",
        "| system | range of motion (m) | VPT threshold (m) | chaotic runs of 50 | training time, all "
        "models (s) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for s in systems:
        e = report["systems"][s]
        lines.append(
            f"| {s} | {e['range_of_motion_m']:.2f} | {e['vpt_threshold_m']:.3f} | {e['chaotic_runs']} | "
            f"{e['train_seconds_total']:.0f} |"
        )
    lines += [
        "",
        f"Plots: `{c['name']}_loss_<system>.png` (training and validation loss), "
        f"`{c['name']}_rollout_<system>.png`"
        " (error over time on the held-out runs, and one rollout).",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--systems", nargs="+", choices=SYSTEMS, default=list(SYSTEMS))
    parser.add_argument("--models", nargs="+", choices=MODELS, default=list(MODELS))
    parser.add_argument("--order", type=int, choices=(2, 4), default=4, help="collocation stencils (4)")
    args = parser.parse_args()
    start = time.perf_counter()
    report = run(args)
    report["seconds"] = time.perf_counter() - start
    name = _name(args)
    (RESULTS / f"{name}.json").write_text(json.dumps(report, indent=1))
    (RESULTS / f"{name}.md").write_text(_markdown(report))
    print(json.dumps(report))


if __name__ == "__main__":
    main()
