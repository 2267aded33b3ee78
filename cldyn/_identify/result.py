"""What identify returns: typed, frozen results."""

import dataclasses
import os
import pathlib
from typing import Any

import numpy as np

from .._system import ConstrainedLagrangian
from .base import Candidate
from .report import save as _save


@dataclasses.dataclass(frozen=True)
class Detection:
    """An effect selected in the data.

    **Fields:** `candidate`; `value` (MuJoCo meaning, SI units) and its bootstrap 95% interval `ci`;
    `parameters` (all of the effect's parameters); the evidence `bic_gain`, `t`, `inclusion`,
    `holdout_drop`, `share`; `alternatives`: candidates that the data cannot tell apart from it;
    `round`: the round of the loop that found it; `detected`: whether it passed every criterion;
    `theta`: its regression coefficients; `failed`: the criteria it failed (`"bic_gain"`, `"t"`,
    `"inclusion"`, `"holdout_drop"`, `"share"`, or `"rollout"` where the model with it predicted the
    held-out runs no better).
    """

    candidate: Candidate
    value: float
    ci: tuple[float, float]
    parameters: dict[str, float]
    bic_gain: float
    t: float
    inclusion: float
    holdout_drop: float
    share: float
    alternatives: tuple[str, ...]
    round: int
    detected: bool
    theta: np.ndarray = dataclasses.field(repr=False, default_factory=lambda: np.zeros(0))
    failed: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        """The effect's name, e.g. `"joint_damping"`."""
        return self.candidate.name

    @property
    def where(self) -> str:
        """The joint, actuator or keypoint."""
        return self.candidate.where

    def refitted(self, parameters: dict[str, float] | None) -> "Detection":
        """The detection with the values a refit gave; the bootstrap interval moves with the value."""
        if parameters is None or not np.isfinite(parameters["value"]):
            return self
        shift = parameters["value"] - self.value
        return dataclasses.replace(
            self,
            value=parameters["value"],
            ci=(self.ci[0] + shift, self.ci[1] + shift),
            parameters={**self.parameters, **parameters},
        )

    def to_dict(self) -> dict[str, Any]:
        """The report entry."""
        c = self.candidate
        out = {"effect": c.name, "where": c.where, "value": self.value, "ci": list(self.ci)}
        if c.kind:
            out["kind"] = c.kind
        extra = {k: v for k, v in self.parameters.items() if k != "value"}
        if extra:
            out["parameters"] = extra
        out["evidence"] = {
            "bic_gain": self.bic_gain,
            "t": self.t,
            "bootstrap_inclusion": self.inclusion,
            "holdout_drop": self.holdout_drop,
            "share": self.share,
        }
        out["alternatives"] = list(self.alternatives)
        out["round"] = self.round
        if self.failed:
            out["failed"] = list(self.failed)
        return out


@dataclasses.dataclass(frozen=True)
class Round:
    """One round of selection: how many candidates, which were selected, which passed, and their
    bootstrap inclusion."""

    round: int
    candidates: int
    selected: tuple[str, ...]
    detected: tuple[str, ...]
    inclusion: dict[str, float]

    def to_dict(self) -> dict[str, Any]:
        """The report entry."""
        return {
            "round": self.round,
            "candidates": self.candidates,
            "selected": list(self.selected),
            "detected": list(self.detected),
            "inclusion": dict(self.inclusion),
        }


@dataclasses.dataclass(frozen=True)
class Errors:
    """A model's errors on the held-out runs.

    **Fields:**

    - `accel_rmse`: m/s^2, the model's keypoint accelerations against the measured ones, both averaged
      over the test functions (so that no second difference of noisy positions is involved).
    - `rollout_rmse_1s`: m, keypoint positions over rollouts of `horizon` seconds from the start of each
      held-out run, against the measurement; each model estimates its own initial state from the first
      0.2 s of the run (Gauss-Newton on its rollout), so that noise in the initial velocity does not
      swamp the comparison.
    - `horizon`: the rollout length in seconds.
    - `unconverged`: runs whose initial-state fit did not converge (their rollouts still count).
    - `diverged`: runs whose rollout turned non-finite (their error is infinite, and so is
      `rollout_rmse_1s`).
    """

    accel_rmse: float
    rollout_rmse_1s: float
    horizon: float
    unconverged: int = 0
    diverged: int = 0

    def to_dict(self) -> dict[str, float]:
        """The report entry."""
        return {
            "accel_rmse": self.accel_rmse,
            "rollout_rmse_1s": self.rollout_rmse_1s,
            "horizon": self.horizon,
        }


@dataclasses.dataclass(frozen=True)
class Adequacy:
    """What the data can support.

    **Fields:**

    - `problems`: why the data cannot support a conclusion (too short, too noisy, motion faster than
      the sampling resolves); empty when they can. With problems and nothing detected, the outcome is
      "nothing could be detected", not "nothing detected".
    - `unexamined`: `(candidate label, reason)` for candidates left out because the data cannot show
      them (a joint that never moves, a control that never varies).
    - `detectable_share`: the smallest effect, as a share of the inertial forces, that would pass the
      BIC criterion through the noise of these data (an effect unlike the model's forces; estimated by
      passing simulated noise of the estimated level through the weak equations).
    - `equations`: independent weak equations per joint in the fit runs.
    """

    problems: tuple[str, ...]
    unexamined: tuple[tuple[str, str], ...]
    detectable_share: float
    equations: float

    @property
    def adequate(self) -> bool:
        """Whether the data can support a conclusion."""
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        """The report entry."""
        return {
            "adequate": self.adequate,
            "problems": list(self.problems),
            "unexamined": [{"candidate": label, "reason": why} for label, why in self.unexamined],
            "detectable_share": self.detectable_share,
            "equations": self.equations,
        }


@dataclasses.dataclass(frozen=True)
class Curves:
    """The held-out keypoint errors over time, `(runs, T, keypoints)`, before and after."""

    ts: np.ndarray
    before: np.ndarray
    after: np.ndarray


@dataclasses.dataclass(frozen=True)
class Scatter:
    """For the partial-residual plot: a detected effect's weak generalised force on the held-out runs
    `(runs, n, m)` and the residual it was selected against."""

    label: str
    feature: np.ndarray
    residual: np.ndarray
    round: int


@dataclasses.dataclass(frozen=True)
class Identification:
    """The outcome of `identify`: what was found, the model with it, and the errors before and after.

    **Fields:**

    - `detected`: the `Detection`s that passed every criterion, strongest first in each round.
    - `rejected`: the candidates that were selected but failed a criterion (for the record).
    - `before`, `after`: the nominal and the final model's `Errors` on the held-out runs.
    - `model`: the augmented, refitted `ConstrainedLagrangian`; `nominal`: the model it started from.
    - `settings`: everything needed to reproduce the run (JSON-able).
    - `rounds`: one `Round` per round of the loop.
    - `warnings`: what did not go as it should (a refit or an initial-state fit that did not
      converge, detections whose held-out rollouts got worse, joint limits reached, a residual that
      asks for an effect of a sign no physical effect has, float32 arithmetic); also in the report.
    - `adequacy`: what the data can support (`Adequacy`).
    - `curves`, `scatter`: the data of the plots.
    """

    detected: tuple[Detection, ...]
    rejected: tuple[Detection, ...]
    before: Errors
    after: Errors
    model: ConstrainedLagrangian
    nominal: ConstrainedLagrangian
    settings: dict[str, Any]
    rounds: tuple[Round, ...]
    warnings: tuple[str, ...] = ()
    adequacy: Adequacy | None = None
    curves: Curves | None = dataclasses.field(repr=False, default=None)
    scatter: tuple[Scatter, ...] = dataclasses.field(repr=False, default=())

    @property
    def outcome(self) -> str:
        """`"detected"` when an effect was found; otherwise `"nothing detected"` where the data could
        have shown one, `"nothing could be detected"` where they cannot support a conclusion (see
        `adequacy.problems`)."""
        if self.detected:
            return "detected"
        if self.adequacy is not None and not self.adequacy.adequate:
            return "nothing could be detected"
        return "nothing detected"

    @property
    def improvement(self) -> dict[str, float]:
        """Before / after for each error."""
        out = {}
        for key in ("accel_rmse", "rollout_rmse_1s"):
            before, after = getattr(self.before, key), getattr(self.after, key)
            out[key] = before / after if after > 0 else float("inf")
        return out

    def to_dict(self) -> dict[str, Any]:
        """The content of `report.json`."""
        return {
            "outcome": self.outcome,
            "detected": [d.to_dict() for d in self.detected],
            "before": self.before.to_dict(),
            "after": self.after.to_dict(),
            "improvement": self.improvement,
            "rejected": [d.to_dict() for d in self.rejected],
            "rounds": [r.to_dict() for r in self.rounds],
            "warnings": list(self.warnings),
            "adequacy": None if self.adequacy is None else self.adequacy.to_dict(),
            "settings": self.settings,
        }

    def summary(self) -> str:
        """A few human-readable lines."""
        lines = []
        if self.outcome == "nothing could be detected":
            lines.append("nothing could be detected: " + "; ".join(self.adequacy.problems))
        elif not self.detected:
            lines.append("no missing effect detected")
        for d in self.detected:
            c = d.candidate
            alt = f" (or: {', '.join(d.alternatives)})" if d.alternatives else ""
            lines.append(
                f"detected {c.name}{'/' + c.kind if c.kind else ''} at {c.where}: {d.value:.4g} "
                f"[{d.ci[0]:.4g}, {d.ci[1]:.4g}]{alt}"
            )
        for key, unit in (("accel_rmse", "m/s^2"), ("rollout_rmse_1s", "m")):
            b, a = getattr(self.before, key), getattr(self.after, key)
            lines.append(f"{key}: {b:.4g} -> {a:.4g} {unit} ({b / a:.1f}x)" if a > 0 else f"{key}: {b:.4g}")
        if self.detected and self.adequacy is not None and not self.adequacy.adequate:
            lines += [f"caution: {p}" for p in self.adequacy.problems]
        if self.adequacy is not None:
            reasons: dict[str, list[str]] = {}
            for label, why in self.adequacy.unexamined:
                reasons.setdefault(why, []).append(label)
            lines += [f"not examined: {why}: {', '.join(labels)}" for why, labels in reasons.items()]
        lines += [f"warning: {w}" for w in self.warnings]
        seconds = self.settings.get("seconds")
        if seconds is not None:
            lines.append(f"identify took {seconds:.1f} s")
        return "\n".join(lines)

    def save(self, directory: "str | os.PathLike") -> pathlib.Path:
        """Write `report.json`, `report.md` and the plots (with matplotlib, the `vision` extra) into
        `directory`, created if needed."""
        return _save(self, directory)
