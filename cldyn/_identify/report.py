"""The identification report: `report.json`, `report.md` and the plots."""

import json
import os
import pathlib
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from .._misc import atomic_save, atomic_write, optional_import

if TYPE_CHECKING:
    from .result import Identification


def _json_default(value):
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def markdown(report: dict[str, Any]) -> str:
    """`report.md` from the content of `report.json`."""
    lines = ["# Missing physics: identification report", ""]
    adequacy = report.get("adequacy") or {}
    if report["detected"]:
        lines += [
            "| effect | where | value | 95% interval | BIC gain | t | bootstrap | held-out drop "
            "| alternatives |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for d in report["detected"]:
            ev = d["evidence"]
            name = d["effect"] + (f" ({d['kind']})" if "kind" in d else "")
            lines.append(
                f"| {name} | {d['where']} | {d['value']:.4g} | [{d['ci'][0]:.4g}, {d['ci'][1]:.4g}] | "
                f"{ev['bic_gain']:.1f} | {ev['t']:.1f} | {ev['bootstrap_inclusion']:.2f} | "
                f"{100 * ev['holdout_drop']:.1f}% | {', '.join(d['alternatives']) or '-'} |"
            )
    elif adequacy.get("problems"):
        lines.append("Nothing could be detected: the data cannot support a conclusion.")
        lines += [""] + [f"- {p}" for p in adequacy["problems"]]
    else:
        lines.append("No missing effect passed the detection criteria.")
    lines += [
        "",
        "| held-out error | before | after | ratio |",
        "| --- | --- | --- | --- |",
    ]
    for key, unit in (("accel_rmse", "m/s^2"), ("rollout_rmse_1s", "m")):
        b, a = report["before"][key], report["after"][key]
        lines.append(f"| {key} ({unit}) | {b:.4g} | {a:.4g} | {b / a if a else float('inf'):.2f}x |")
    if report["rejected"]:
        lines += ["", "Selected but not detected (failed a criterion):", ""]
        for d in report["rejected"]:
            ev = d["evidence"]
            lines.append(
                f"- {d['effect']} at {d['where']}: {d['value']:.3g} (BIC gain {ev['bic_gain']:.1f}, "
                f"t {ev['t']:.1f}, bootstrap {ev['bootstrap_inclusion']:.2f}, "
                f"held-out drop {100 * ev['holdout_drop']:.1f}%, share {100 * ev['share']:.2f}%)"
            )
    if adequacy.get("unexamined"):
        lines += ["", "Not examined (the data cannot show them):", ""]
        lines += [f"- {u['candidate']}: {u['reason']}" for u in adequacy["unexamined"]]
    if report["warnings"]:
        lines += ["", "Warnings:", ""] + [f"- {w}" for w in report["warnings"]]
    s = report["settings"]
    sm = s["smoothing"]
    lines += [
        "",
        f"Data: {s['runs']} runs ({len(s['held_out_runs'])} held out) of {s['samples']} samples every "
        f"{1e3 * s['dt']:.4g} ms; position noise {1e3 * sm['noise']:.3g} mm (estimated), motion time scale "
        f"{1e3 * sm['timescale_seconds']:.3g} ms; smallest detectable effect "
        f"{100 * adequacy.get('detectable_share', float('nan')):.2g}% of the inertial forces; "
        f"{100 * s['excluded_equations']:.0f}% of the equations excluded.",
        "",
        f"Velocities: Savitzky-Golay, window {1e3 * sm['window_seconds']:.4g} ms ({sm['window']} samples), "
        f"order {sm['order']}; kept every {sm['decimation']} samples "
        f"({1e3 * sm['interval_seconds']:.4g} ms); "
        f"equations in weak form, test functions of {1e3 * sm['test_width_seconds']:.4g} ms every "
        f"{1e3 * sm['test_stride_seconds']:.4g} ms. How each was set: {sm['chosen']}.",
        "",
        f"Criteria: {s['criteria']}. {s['bootstrap']} bootstrap replicates, seed {s['seed']}; "
        f"identify took {s['seconds']:.1f} s.",
        "",
        "Plots: `residual_vs_feature.png`, `error_over_time.png`.",
        "",
    ]
    return "\n".join(lines)


def _error_over_time(figure, result: "Identification"):
    with warnings.catch_warnings():  # samples after every run's first contact with a joint limit
        warnings.simplefilter("ignore", RuntimeWarning)
        return _draw_error_over_time(figure, result)


def _draw_error_over_time(figure, result: "Identification"):
    curves = result.curves
    fig = figure(figsize=(6, 4))
    ax = fig.subplots()
    for key, style in (("before", "C3"), ("after", "C2")):
        err = getattr(curves, key)  # (runs, T, keypoints); NaN after a joint limit is reached
        mean = np.nanmean(err, axis=(0, 2))
        rmse = 1e3 * np.sqrt(np.nanmean(err**2))
        ax.plot(curves.ts, 1e3 * mean, style, label=f"{key}: rmse {rmse:.2f} mm")
        ax.fill_between(
            curves.ts,
            1e3 * np.nanpercentile(err.mean(2), 10, axis=0),
            1e3 * np.nanpercentile(err.mean(2), 90, axis=0),
            color=style,
            alpha=0.15,
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("keypoint position error (mm)")
    ax.set_title("Held-out rollouts: nominal vs. identified model")
    ax.legend()
    fig.tight_layout()
    return fig


def _residual_vs_feature(figure, result: "Identification"):
    scatter = result.scatter
    n = max(1, len(scatter))
    fig = figure(figsize=(4.5 * n, 4))
    axes = fig.subplots(1, n, squeeze=False)
    for index, (ax, item) in enumerate(zip(axes[0], scatter)):
        feature = item.feature  # (runs, n, m): the effect's generalised force, weak form
        # the partial residual: what is left for this effect once the other detected effects are removed
        residual = item.residual - sum(
            other.feature for j, other in enumerate(scatter) if j != index and other.round == item.round
        )
        component = int(np.argmax(np.mean(feature**2, axis=(0, 1))))
        f = feature[..., component].reshape(-1)
        r = residual[..., component].reshape(-1)
        pick = np.random.default_rng(0).permutation(f.size)[:4000]
        ax.plot(f[pick], r[pick], ".", ms=2, alpha=0.4, color="C0", label="held-out residual")
        line = np.linspace(f.min(), f.max(), 2)
        ax.plot(line, line, "C3", label="identified effect")
        ax.set_xlabel(f"{item.label} force (joint {component})")
        ax.set_ylabel("partial residual generalised force")
        ax.legend(fontsize=8)
    if not scatter:
        axes[0][0].text(0.5, 0.5, "no effect detected", ha="center", va="center")
    fig.tight_layout()
    return fig


def _plots(result: "Identification", directory: pathlib.Path) -> None:
    # matplotlib's object-oriented Figure draws without pyplot: no backend is chosen, no global state
    figure = optional_import("matplotlib.figure", purpose="Identification.save's plots").Figure
    for name, draw in (
        ("error_over_time.png", _error_over_time),
        ("residual_vs_feature.png", _residual_vs_feature),
    ):
        fig = draw(figure, result)
        atomic_save(directory / name, lambda path, fig=fig: fig.savefig(path, dpi=120))


def save(result: "Identification", directory: "str | os.PathLike") -> pathlib.Path:
    """Write `report.json`, `report.md` and the plots into `directory` (created if needed)."""
    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    report = result.to_dict()
    atomic_write(directory / "report.json", json.dumps(report, indent=2, default=_json_default))
    atomic_write(directory / "report.md", markdown(report))
    if result.curves is not None:
        _plots(result, directory)
    return directory
