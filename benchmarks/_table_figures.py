"""The figures of `vision_table.py`: Fig. 3 (image error over time) and Figs. 4 and 13-15 (predicted
frames beside the true ones)."""

import pathlib

import numpy as np

FRAME_EVERY = 4  # frames between those of Figs. 4 and 13-15


def errors(mse_per_run) -> np.ndarray:
    """`keyvision evaluate`'s errors per run and frame, a failed prediction's (null) as infinite."""
    return np.nan_to_num(np.asarray(mse_per_run, dtype=float), nan=np.inf)


def plot_mse(path: pathlib.Path, scene: str, rows: dict) -> None:
    """Fig. 3: each row's image error over time, the median over its runs with the quartiles as a band,
    the VPT threshold dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(5.5, 3.4), constrained_layout=True)
    threshold = None
    for name, row in rows.items():
        mse = errors(row["mse_per_run"])
        t = np.arange(mse.shape[1]) * row["dt"]
        (line,) = axes.plot(t, np.median(mse, axis=0), label=name)
        low, high = np.percentile(mse, [25, 75], axis=0, method="nearest")
        axes.fill_between(t, low, high, color=line.get_color(), alpha=0.2)
        threshold = row["threshold"]
    axes.axhline(threshold, color="k", linestyle="--", label="threshold")
    axes.set(xlabel="time (s)", ylabel="MSE (median, quartiles)", yscale="log", title=scene)
    axes.legend(fontsize=7)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_frames(path: pathlib.Path, data: pathlib.Path, models: dict, run: int = 0) -> None:
    """Figs. 4 and 13-15: every `FRAME_EVERY`-th frame of validation run `run`, true and as each model
    predicts it; `models` maps a row's name to (model directory, the stage evaluated or None)."""
    import equinox as eqx
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import keyvision

    validation = keyvision.Frames.load(data / "frames.npz").split()[1]
    images = validation.images(np.float32)[run]
    rows = {"ground truth": images}
    for name, (directory, stage) in models.items():
        model, _ = keyvision.load_model(directory, stage=stage)
        predict = eqx.filter_jit(keyvision.predict)
        rows[name] = np.asarray(predict(model, images, validation.u[run].astype(np.float32), validation.dt))
    shown = range(0, images.shape[0], FRAME_EVERY)
    figure, axes = plt.subplots(
        len(rows), len(shown), figsize=(0.8 * len(shown), 0.85 * len(rows)), squeeze=False
    )
    for r, (name, frames) in enumerate(rows.items()):
        for c, t in enumerate(shown):
            axes[r, c].imshow(np.clip(frames[t], 0, 1))
            axes[r, c].set_xticks([])
            axes[r, c].set_yticks([])
            if c == 0:
                axes[r, c].set_ylabel(name, fontsize=6, rotation=0, ha="right", va="center")
            if r == 0:
                axes[r, c].set_title(str(t), fontsize=6)
    figure.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(figure)
