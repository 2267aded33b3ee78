"""Shared helpers for the benchmark scripts: machine description and result files."""

import datetime
import json
import os
import pathlib
import platform

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def repo_path(path) -> str:
    """`path` as result files keep it: relative to the repository where it lies inside, else absolute."""
    path, root = pathlib.Path(path).resolve(), RESULTS.parents[1]
    return str(path.relative_to(root) if path.is_relative_to(root) else path)


# the models learnt from images that the vision benchmarks use: the shipped pendulum, the committed others
VISION_MODELS = {
    "pendulum": RESULTS.parents[1] / "keyvision" / "demo" / "pendulum",
    "cartpole": RESULTS / "vision_models" / "cartpole",
    "acrobot": RESULTS / "vision_models" / "acrobot",
}


def machine() -> dict:
    """What the numbers were measured on."""
    import jax

    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
    }


def write(name: str, result: dict, markdown: str | None = None) -> None:
    """Write `results/<name>.json` (and `.md`), and print the JSON object."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    text = json.dumps(result, indent=2)
    (RESULTS / f"{name}.json").write_text(text + "\n")
    if markdown is not None:
        (RESULTS / f"{name}.md").write_text(markdown)
    print(text)
