"""`keyvision render`: an image dataset of a planar MuJoCo scene in the KeyCLD protocol."""

import argparse
import pathlib
import time

from cldyn._cli._common import CommandError, add_command, add_overwrite, output_directory, positive, seed

from ._common import FRAMES_NAME

SCENE_HELP = (
    "keycld/<pendulum|cartpole|acrobot>, an MJCF file or a dm_control suite name (a planar scene with a "
    "fixed camera)"
)


def register(subparsers) -> None:
    """Add `keyvision render`."""
    parser = add_command(
        subparsers,
        "render",
        help="render an image dataset of a MuJoCo scene",
        description="Render random runs of a planar MuJoCo scene seen by a fixed camera, in the KeyCLD "
        "paper's protocol (appendix A.6): random initial states, one random constant control per run, "
        "the scene's timestep between frames. The frames and their ground truth (joint states, keypoints, "
        "the camera map) go to --out/frames.npz; the dataset is also cached under a hash of the request, "
        "so rendering it again only loads it.",
    )
    count = positive(integer=True)
    parser.add_argument("--scene", required=True, help=SCENE_HELP)
    parser.add_argument("--out", required=True, help="output directory (frames.npz is written there)")
    parser.add_argument("--runs", type=count, default=500, help="number of runs")
    parser.add_argument("--frames", type=count, default=50, help="frames per run")
    parser.add_argument("--size", type=count, default=64, help="side of the square frames in pixels")
    parser.add_argument(
        "--supersample",
        type=count,
        default=1,
        help="each pixel the mean of N x N samples, as a camera integrates light over a pixel (1: MuJoCo's "
        "render, the paper's frames; see keyvision.RenderProtocol)",
    )
    parser.add_argument(
        "--validation-runs",
        type=positive(integer=True, allow_zero=True),
        default=50,
        help="the last N runs are for validation",
    )
    parser.add_argument("--seed", type=seed, default=0, help="seed of the initial states and controls")
    parser.add_argument("--camera", default="fixed", help="name of a camera fixed in the world")
    parser.add_argument(
        "--keypoints",
        nargs="+",
        metavar="SITE",
        default=None,
        help="sites of the scene whose positions are the keypoints, in order (default: the moving joint "
        "anchors and the far ends of the last bodies and of turning bodies that carry no hinge)",
    )
    parser.add_argument(
        "--workers", type=count, default=None, help="worker processes (default: CPUs; 1: in this process)"
    )
    parser.add_argument(
        "--cache",
        default=None,
        help="cache directory (default: keyvision.cache_directory(), $KEYVISION_CACHE or ~/.cache/keyvision)",
    )
    parser.add_argument(
        "--no-cache", dest="use_cache", action="store_false", help="neither read nor write a cache"
    )
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress lines")
    add_overwrite(parser, "frames")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Render (or load from the cache), save, print one line."""
    if args.validation_runs > args.runs:
        raise CommandError(f"--validation-runs {args.validation_runs}: more than the {args.runs} runs")
    if args.cache is not None and not args.use_cache:
        raise CommandError("--cache names a cache and --no-cache asks for none: give one")
    out = output_directory(args.out, results=(FRAMES_NAME,), overwrite=args.overwrite)
    import cldyn
    import keyvision

    protocol = keyvision.RenderProtocol(
        runs=args.runs,
        frames=args.frames,
        image_size=args.size,
        validation_runs=args.validation_runs,
        supersample=args.supersample,
    )
    cache = pathlib.Path(args.cache) if args.cache is not None else keyvision.cache_directory()
    start = time.time()
    frames = keyvision.render(
        args.scene,
        camera=args.camera,
        protocol=protocol,
        keypoints=args.keypoints,
        seed=args.seed,
        cache=cache if args.use_cache else False,
        workers=args.workers,
        progress_meter=cldyn.TextProgressMeter() if args.progress else cldyn.NoProgressMeter(),
    )
    path = frames.save(out / FRAMES_NAME)
    seconds = time.time() - start
    done, where = "rendered", "no cache"
    if args.use_cache:
        cached = sorted(cache.glob(f"*-{frames.info['cache_key'][:16]}.npz"))
        if cached and cached[0].stat().st_mtime < start:  # an earlier render of the same request
            done, where = "loaded", f"loaded from the cache {cached[0]}"
        elif cached:
            where = f"cached in {cached[0]}"
    height, width = frames.image_size
    camera = f", {args.supersample}x{args.supersample} samples per pixel" if args.supersample > 1 else ""
    print(
        f"{done} {frames.num_runs} runs x {frames.num_frames} frames of {height}x{width} pixels{camera} "
        f"({frames.info['validation_runs']} runs for validation, dt {frames.dt:g} s) of {args.scene} "
        f"in {seconds:.1f} s; {where}; wrote {path}"
    )
    return 0
