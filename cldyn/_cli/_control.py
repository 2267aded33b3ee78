"""`cldyn control`: energy-shaping swing-up (eq. 32) of a MuJoCo scene with an analytic or learned model."""

import argparse
import json
import time

from ._common import add_command, add_overwrite, enable_float64, output_directory, positive, seed

RESULTS = ("control.json", "control.png")

DAMPING_FORMS = ("keypoint", "output")


def register(subparsers) -> None:
    """Add `cldyn control`."""
    parser = add_command(
        subparsers,
        "control",
        help="energy-shaping swing-up of a MuJoCo scene with an analytic or learned model",
        description="Swing a fully actuated scene from hanging to upright with cldyn.EnergyShaping (eq. 32) "
        "as a keypoint feedback policy on MuJoCo, over random starts; report the success rate.",
    )
    parser.add_argument(
        "--mjcf", required=True, help="scene: file, suite name or keycld/<pendulum|cartpole|acrobot>"
    )
    parser.add_argument("--out", required=True, help="output directory for control.json and control.png")
    parser.add_argument(
        "--model", default=None, help="a `cldyn fit` output directory (default: the analytic model)"
    )
    parser.add_argument("--kp", type=positive(), default=5.0, help="stiffness of the shaped potential")
    parser.add_argument("--kd", type=positive(allow_zero=True), default=2.0, help="damping gain")
    parser.add_argument("--damping", choices=DAMPING_FORMS, default="keypoint", help="damping form")
    parser.add_argument("--runs", type=positive(integer=True), default=20, help="random starts")
    parser.add_argument("--duration", type=positive(), default=10.0, help="seconds per run")
    parser.add_argument("--seed", type=seed, default=0, help="seed of the starts")
    add_overwrite(parser, "control.json and control.png")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Swing up, write control.json and control.png, print one line."""
    out = output_directory(args.out, results=RESULTS, overwrite=args.overwrite)
    enable_float64()
    import jax

    import cldyn
    from cldyn.mujoco import keycld_origin, plot_swing_up, swing_up

    from .._misc import atomic_write

    system, origin = None, None
    if args.model is not None:
        system, _ = cldyn.load_fit(args.model)
        # trained in float32; the controller runs beside MuJoCo in float64
        system = jax.tree_util.tree_map(lambda a: a.astype(float) if hasattr(a, "astype") else a, system)
        if args.mjcf.startswith("keycld/"):
            origin = tuple(float(v) for v in keycld_origin(args.mjcf.removeprefix("keycld/")))
    started = time.perf_counter()
    result = swing_up(
        args.mjcf,
        kp=args.kp,
        kd=args.kd,
        damping=args.damping,
        system=system,
        origin=origin,
        runs=args.runs,
        duration=args.duration,
        seed=args.seed,
        progress_meter=cldyn.TqdmProgressMeter(),
    )
    summary = {k: v for k, v in result.items() if k not in ("ts", "errors", "recording")}
    summary["model"] = str(args.model) if args.model else "from_mjcf (analytic)"
    summary["seconds"] = time.perf_counter() - started
    atomic_write(out / "control.json", json.dumps(summary, indent=2))
    plot_swing_up([result], out / "control.png")
    print(
        f"{args.mjcf}: {100 * result['success_rate']:.0f}% of {args.runs} runs within "
        f"{result['tolerance']} m of upright after {args.duration:g} s; "
        f"wrote {out / 'control.json'} and {out / 'control.png'}"
    )
    return 0
