"""`cldyn identify`: find the physics a nominal MJCF model is missing in recorded data."""

import argparse

from ._common import (
    CommandError,
    add_command,
    add_overwrite,
    enable_float64,
    fraction,
    input_file,
    output_directory,
    positive,
    seed,
)

# what Identification.save writes
REPORT_FILES = ("report.json", "report.md", "error_over_time.png", "residual_vs_feature.png")


def add_effects_option(parser) -> None:
    """`--effects`: the effects of the library to consider (all by default)."""
    from .. import EFFECTS

    effects = [effect.name for effect in EFFECTS]
    parser.add_argument(
        "--effects",
        nargs="+",
        default=effects,
        choices=effects,
        metavar="EFFECT",
        help=f"effects to consider, of {', '.join(effects)} (default: all)",
    )


def register(subparsers) -> None:
    """Add `cldyn identify`."""
    parser = add_command(
        subparsers,
        "identify",
        help="find the physics a nominal MJCF model is missing in recorded data",
        description=(
            "Compute the residual of the nominal model on recorded data, attribute it to effects of the "
            "library (damping, Coulomb friction, springs, armature, actuator gain, drag, point masses), "
            "add them, refit, and report the error before and after."
        ),
    )
    parser.add_argument("--data", required=True, help="a recording saved by `cldyn record` (.npz)")
    parser.add_argument(
        "--model",
        required=True,
        help="the nominal MJCF (file, suite name, cartpole/two_poles or keycld/<name>)",
    )
    parser.add_argument("--out", required=True, help="directory for report.json/md and plots")
    add_effects_option(parser)
    count = positive(integer=True)
    parser.add_argument("--bootstrap", type=count, default=100, help="bootstrap replicates")
    parser.add_argument("--holdout", type=fraction, default=0.25, help="fraction of runs held out")
    parser.add_argument("--max-rounds", type=count, default=3, help="detect-augment-refit rounds")
    seconds = positive()
    parser.add_argument(
        "--window",
        type=seconds,
        default=None,
        help="Savitzky-Golay window in seconds (default: chosen from the data's noise and motion)",
    )
    parser.add_argument("--order", type=count, default=6, help="Savitzky-Golay polynomial order (>= 2)")
    parser.add_argument(
        "--test-width",
        type=seconds,
        default=None,
        help="weak-form test function width in seconds (default: twice the motion's time scale)",
    )
    parser.add_argument(
        "--test-stride",
        type=seconds,
        default=None,
        help="seconds between test functions (default: a sixth of the width)",
    )
    parser.add_argument(
        "--no-decimation",
        dest="decimate",
        action="store_false",
        help="keep every sample (by default fast data are thinned out after smoothing)",
    )
    parser.add_argument("--seed", type=seed, default=0, help="seed of the split and the bootstrap")
    add_overwrite(parser, "a report")
    parser.set_defaults(run=run)


def narrative(result) -> str:
    """What the identification did: the data and the settings chosen from them, round by round."""
    settings = result.settings
    runs, held = settings["runs"], len(settings["held_out_runs"])
    sm = settings["smoothing"]

    def errors(name, e):
        return f"  {name}: accel_rmse {e.accel_rmse:.4g} m/s^2, rollout_rmse_1s {e.rollout_rmse_1s:.4g} m"

    lines = [
        f"identify: {runs} runs ({runs - held} fit, {held} held out) of {settings['samples']} samples every "
        f"{1e3 * settings['dt']:.4g} ms",
        f"  noise {1e3 * sm['noise']:.3g} mm (estimated), motion time scale "
        f"{1e3 * sm['timescale_seconds']:.3g} ms; smoothing window {1e3 * sm['window_seconds']:.4g} ms, test "
        f"functions {1e3 * sm['test_width_seconds']:.4g} ms, a sample kept every "
        f"{1e3 * sm['interval_seconds']:.4g} ms",
    ]
    lines.append(errors("before", result.before))
    lines += [f"  round {r.round}: " + ("; ".join(r.detected) or "nothing passes") for r in result.rounds]
    lines.append(errors("after", result.after))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Identify, save the report, print its summary."""
    if args.order < 2:
        raise CommandError(f"--order {args.order}: must be at least 2")
    path = input_file(args.data, "--data")
    out = output_directory(args.out, results=REPORT_FILES, overwrite=args.overwrite)
    enable_float64()
    import cldyn
    from cldyn.mujoco import identify_recording

    data = cldyn.Sequences.load(path)
    smoothing = cldyn.Smoothing(
        window=args.window,
        order=args.order,
        test_width=args.test_width,
        test_stride=args.test_stride,
        decimate=args.decimate,
    )
    try:
        result = identify_recording(
            data,
            args.model,
            effects=tuple(args.effects),
            smoothing=smoothing,
            criteria=cldyn.Criteria(),
            bootstrap=args.bootstrap,
            holdout=args.holdout,
            max_rounds=args.max_rounds,
            seed=args.seed,
            progress_meter=cldyn.TqdmProgressMeter(),
        )
    except cldyn.ConstraintViolation as error:
        raise CommandError(f"--data {path} does not fit --model {args.model}: {error}") from None
    report = result.save(out)
    print(narrative(result))
    print(result.summary())
    print(f"wrote {report / 'report.json'}, {report / 'report.md'} and plots")
    return 0
