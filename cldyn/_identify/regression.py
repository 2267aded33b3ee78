"""Attribution: sparse, sign-constrained least squares on the weak residual, with forward selection
by the Bayesian information criterion, equivalence classes and a bootstrap over whole runs."""

import dataclasses
import itertools
import math
from collections.abc import Sequence

import equinox as eqx
import numpy as np

from .base import Candidate
from .result import Detection, Round


class Criteria(eqx.Module):
    """When an effect counts as detected: every criterion must hold.

    **Arguments:**

    - `min_bic_gain`: removing the effect from the selected set must raise the Bayesian information
      criterion by at least this much (10 is "very strong" evidence). The BIC counts one independent
      sample per smoothing window, since smoothing correlates neighbouring residuals.
    - `min_t`: |estimate| / bootstrap standard error (the bootstrap resamples whole trajectories).
    - `min_inclusion`: the fraction of bootstrap replicates whose own selection includes the effect.
    - `min_holdout_drop`: the relative drop of the held-out residual sum of squares when the effect
      is added to the others.
    - `min_share`: the effect's generalised force, RMS, relative to the RMS of the inertial forces
      `G^T M xdd`: smaller effects do not matter to the motion and are not reported.

    And when the data can support a conclusion at all (else "nothing could be detected"):

    - `min_equations`: independent weak equations per joint in the fit runs, at least.
    - `max_detectable_share`: the smallest effect the noise lets through (as a share of the inertial
      forces, see `Adequacy.detectable_share`) must not exceed this.
    - `min_samples_per_timescale`: samples per time scale of the motion, at least (motion faster than
      this is not resolved by the sampling).

    Whatever the criteria, a detection stands only where the model with it predicts the held-out runs
    better than without it: a lower held-out rollout error.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                criteria=cldyn.Criteria(min_bic_gain=20.0))
        ```
    """

    min_bic_gain: float = eqx.field(static=True, default=10.0)
    min_t: float = eqx.field(static=True, default=4.0)
    min_inclusion: float = eqx.field(static=True, default=0.9)
    min_holdout_drop: float = eqx.field(static=True, default=0.05)
    min_share: float = eqx.field(static=True, default=0.003)
    min_equations: float = eqx.field(static=True, default=20.0)
    max_detectable_share: float = eqx.field(static=True, default=0.05)
    min_samples_per_timescale: float = eqx.field(static=True, default=3.0)

    def to_dict(self) -> dict[str, float]:
        """The criteria by name, for reports."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


# -- least squares on normal equations -----------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Normal:
    """Sufficient statistics of weighted least squares: `A = Phi^T Phi`, `b = Phi^T r`, `c = r^T r`,
    and the number of equations `n`."""

    A: np.ndarray
    b: np.ndarray
    c: float
    n: int

    def __add__(self, other: "Normal") -> "Normal":
        return Normal(self.A + other.A, self.b + other.b, self.c + other.c, self.n + other.n)

    def rss(self, columns: list[int], theta: np.ndarray) -> float:
        """The residual sum of squares of `theta` on `columns`."""
        if not columns:
            return self.c
        idx = np.asarray(columns)
        return float(self.c - 2 * theta @ self.b[idx] + theta @ self.A[np.ix_(idx, idx)] @ theta)


def fit(normal: Normal, columns: list[int], signs: list[int]) -> tuple[np.ndarray, float]:
    """Least squares on `columns` with `theta_i >= 0` where `signs[i] = 1`; returns `(theta, RSS)`."""
    if not columns:
        return np.zeros(0), normal.c
    idx = np.asarray(columns)
    A = normal.A[np.ix_(idx, idx)]
    b = normal.b[idx]
    constrained = [i for i, s in enumerate(signs) if s > 0]
    best = None
    # The optimum of a convex QP with bounds has some bounded variables at zero and the rest an
    # unconstrained optimum: try the active sets in order of size (the problems here are tiny).
    for size in range(len(constrained) + 1):
        for active in itertools.combinations(constrained, size):
            free = [i for i in range(len(idx)) if i not in active]
            theta = np.zeros(len(idx))
            if free:
                sub = A[np.ix_(free, free)]
                theta[free] = np.linalg.lstsq(sub, b[free], rcond=1e-12)[0]
            if any(theta[i] < 0 for i in constrained):
                continue
            rss = normal.c - 2 * theta @ b + theta @ A @ theta
            if best is None or rss < best[1] - 1e-12 * abs(normal.c):
                best = (theta, float(rss))
        if best is not None:
            break
    return best


def bic(rss: float, n: int, p: int, correlation: float) -> float:
    """The Bayesian information criterion of `p` parameters on `n` equations, `correlation` of which
    make one independent equation."""
    n_eff = max(n / correlation, 2.0)
    return n_eff * math.log(max(rss, 1e-300) / n) + p * math.log(n_eff)


@dataclasses.dataclass(frozen=True)
class Groups:
    """The column layout: candidate `g` owns the columns `columns[g]`; `signs` per column."""

    columns: tuple[tuple[int, ...], ...]
    signs: tuple[int, ...]

    @classmethod
    def of(cls, candidates: Sequence[Candidate]) -> "Groups":
        columns, signs, start = [], [], 0
        for c in candidates:
            columns.append(tuple(range(start, start + len(c.columns))))
            signs += list(c.signs)
            start += len(c.columns)
        return cls(tuple(columns), tuple(signs))

    def select(self, chosen: Sequence[int]) -> tuple[list[int], list[int]]:
        """The columns of the chosen groups and their signs."""
        columns = [c for g in chosen for c in self.columns[g]]
        return columns, [self.signs[c] for c in columns]

    def admissible(self, theta: np.ndarray, chosen: Sequence[int]) -> bool:
        """Whether every sign-constrained coefficient of the chosen groups is positive."""
        _, signs = self.select(chosen)
        return not any(s > 0 and t <= 0 for s, t in zip(signs, theta))


@dataclasses.dataclass(frozen=True)
class Selection:
    """The groups a forward selection chose, with their coefficients, RSS and BIC."""

    groups: tuple[int, ...]
    theta: np.ndarray
    rss: float
    bic: float


def forward_select(
    normal: Normal, groups: Groups, *, correlation: float, min_gain: float, max_groups: int
) -> Selection:
    """Add the group that lowers the BIC most, while it lowers it by `min_gain` or more; groups whose
    admissible fit does not use them are skipped."""
    chosen: list[int] = []
    theta, rss = fit(normal, [], [])
    score = bic(rss, normal.n, 0, correlation)
    while len(chosen) < max_groups:
        best = None
        for g in range(len(groups.columns)):
            if g in chosen:
                continue
            columns, signs = groups.select(chosen + [g])
            theta_g, rss_g = fit(normal, columns, signs)
            width = len(groups.columns[g])
            if any(s > 0 and t <= 0 for s, t in zip(signs[-width:], theta_g[-width:])):
                continue  # the physically admissible fit does not use this candidate at all
            bic_g = bic(rss_g, normal.n, len(columns), correlation)
            if best is None or bic_g < best[2]:
                best = (g, theta_g, bic_g, rss_g)
        if best is None or score - best[2] < min_gain:
            break
        chosen.append(best[0])
        theta, score, rss = best[1], best[2], best[3]
    return Selection(tuple(chosen), theta, rss, score)


# -- one round of attribution --------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Problem:
    """One round's regression: the weak residual and features of the fit and held-out runs.

    **Fields:** `candidates`; `r_fit` `(runs, n, m)`, the residual of the fit runs; `f_fit`
    `(runs, n, m, C)`, their features; `inertial_fit` `(runs, n, m)`, their inertial forces;
    `r_held`, `f_held` the same for the held-out runs; `weights` `(m,)`, per joint; `kept_fit`,
    `kept_held` `(runs, n)`, the equations that count (the others touch excluded samples).
    """

    candidates: tuple[Candidate, ...]
    r_fit: np.ndarray
    f_fit: np.ndarray
    inertial_fit: np.ndarray
    r_held: np.ndarray
    f_held: np.ndarray
    weights: np.ndarray
    kept_fit: np.ndarray
    kept_held: np.ndarray


@dataclasses.dataclass(frozen=True)
class Attribution:
    """The outcome of one round: the selected candidates (passed or not, strongest first), the round's
    summary, and the column layout."""

    selected: tuple[Detection, ...]
    round: Round
    groups: Groups
    inadmissible: tuple["Inadmissible", ...] = ()


@dataclasses.dataclass(frozen=True)
class Inadmissible:
    """A candidate the residual asks for with the sign physics forbids (a negative damping, armature
    or mass, say): strong evidence, by the BIC, that the nominal model overstates what the candidate
    stands for. Never a detection; identify reports it as a warning. `alternatives`: candidates
    that explain the same part of the residual (represented, as in a detection's equivalence class, by
    the one earliest in the order of the effects)."""

    label: str
    value: float
    bic_gain: float
    alternatives: tuple[str, ...] = ()
    candidate: int = 0  # its index in the round's candidates
    theta: np.ndarray = dataclasses.field(repr=False, default_factory=lambda: np.zeros(0))

    def describe(self) -> str:
        same = f"; or {', '.join(self.alternatives)}" if self.alternatives else ""
        return f"{self.label} = {self.value:.3g} (BIC gain {self.bic_gain:.1f}{same})"


def inadmissible(
    normal: Normal,
    groups: Groups,
    candidates: Sequence[Candidate],
    chosen: Sequence[int],
    *,
    correlation: float,
    min_gain: float,
    scale: np.ndarray,
) -> tuple[Inadmissible, ...]:
    """The candidates outside `chosen` that, added with their sign constraints lifted, lower the BIC
    by `min_gain` or more at a coefficient of the forbidden sign; strongest first, one per class of
    candidates that explain the same (adding one to another gains less than `min_gain`)."""
    columns, signs = groups.select(chosen)
    _, rss = fit(normal, columns, signs)
    base = bic(rss, normal.n, len(columns), correlation)

    def free_fit(extra: list[int]) -> tuple[np.ndarray, float]:
        own = [c for g in extra for c in groups.columns[g]]
        theta, rss_g = fit(normal, columns + own, signs + [0] * len(own))
        return theta[len(columns) :], base - bic(rss_g, normal.n, len(columns) + len(own), correlation)

    strong = []
    for g in range(len(candidates)):
        own = list(groups.columns[g])
        if g in chosen or not any(groups.signs[c] > 0 for c in own):
            continue
        theta, gain = free_fit([g])
        if gain >= min_gain and any(groups.signs[c] > 0 and t < 0 for c, t in zip(own, theta)):
            strong.append((gain, g, theta))
    # a candidate that adds less than `min_gain` to a stronger one explains nothing more: it joins that
    # one's class when it explains about as much on its own (within `min_gain`), else it is dropped
    classes: list[list[tuple[float, int, np.ndarray]]] = []
    for item in sorted(strong, key=lambda s: (-s[0], s[1])):
        for members in classes:
            head = members[0]
            if free_fit([head[1], item[1]])[1] - head[0] < min_gain:
                if head[0] - item[0] < min_gain:
                    members.append(item)
                break
        else:
            classes.append([item])
    found = []
    for members in classes:
        gain, g, theta = min(members, key=lambda m: m[1])  # the earliest in the order of the effects
        own = list(groups.columns[g])
        found.append(
            Inadmissible(
                candidates[g].label,
                float(candidates[g].parameters(theta / scale[own])["value"]),
                float(gain),
                tuple(candidates[h].label for _, h, _ in members if h != g),
                g,
                theta / scale[own],
            )
        )
    return tuple(found)


def _per_run_normals(problem: Problem, r, f, kept, scale):
    w = problem.weights[None, None, :, None] * kept[:, :, None, None]
    fw = f * w / scale[None, None, None, :]
    rw = r * w[..., 0]
    A = np.einsum("rtmc,rtmd->rcd", fw, fw)
    b = np.einsum("rtmc,rtm->rc", fw, rw)
    c = np.einsum("rtm,rtm->r", rw, rw)
    n = kept.sum(axis=1) * r.shape[2]
    return A, b, c, n


def _scale(problem: Problem) -> np.ndarray:
    """Per column, the RMS of the weighted features of the counted equations (for conditioning)."""
    kept = problem.kept_fit
    w = problem.weights[None, None, :, None] * kept[:, :, None, None]
    scale = np.sqrt(np.sum((problem.f_fit * w) ** 2, axis=(0, 1, 2)) / max(kept.sum() * w.shape[2], 1))
    return np.where(scale > 0, scale, 1.0)


def coefficients(problem: Problem, chosen: Sequence[int]) -> list[np.ndarray]:
    """The sign-constrained least-squares coefficients of the chosen candidates (indices into
    `problem.candidates`) fitted on their own to the fit runs: one array per candidate, in the
    effects' own units. What the others of a round would be without one of them."""
    groups = Groups.of(problem.candidates)
    scale = _scale(problem)
    A_r, b_r, c_r, n_r = _per_run_normals(problem, problem.r_fit, problem.f_fit, problem.kept_fit, scale)
    columns, signs = groups.select(chosen)
    theta, _ = fit(Normal(A_r.sum(0), b_r.sum(0), float(c_r.sum()), int(n_r.sum())), columns, signs)
    out, offset = [], 0
    for g in chosen:
        own = list(groups.columns[g])
        out.append(theta[offset : offset + len(own)] / scale[own])
        offset += len(own)
    return out


def attribute(
    problem: Problem,
    *,
    correlation: float,
    criteria: Criteria,
    bootstrap: int,
    max_effects: int,
    rng: np.random.Generator,
    round_index: int,
) -> Attribution:
    """Selection, equivalence classes, bootstrap and criteria for one round.

    **Arguments:**

    - `problem`: the round's `Problem`.
    - `correlation`: rows of the weak equations per independent one (`Smoothing.correlation`).
    - `criteria`: the `Criteria` of a detection.
    - `bootstrap`: replicates over whole runs; `max_effects`: the most groups selected.
    - `rng`: for the bootstrap; `round_index`: for the report.
    """
    candidates = problem.candidates
    groups = Groups.of(candidates)
    kept = problem.kept_fit
    scale = _scale(problem)
    A_r, b_r, c_r, n_r = _per_run_normals(problem, problem.r_fit, problem.f_fit, kept, scale)
    total = Normal(A_r.sum(0), b_r.sum(0), float(c_r.sum()), int(n_r.sum()))
    A_h, b_h, c_h, n_h = _per_run_normals(problem, problem.r_held, problem.f_held, problem.kept_held, scale)
    held = Normal(A_h.sum(0), b_h.sum(0), float(c_h.sum()), int(n_h.sum()))
    gain = criteria.min_bic_gain

    def select(normal):
        return forward_select(normal, groups, correlation=correlation, min_gain=gain, max_groups=max_effects)

    def fit_set(normal, chosen):
        columns, signs = groups.select(chosen)
        theta, rss = fit(normal, columns, signs)
        return theta, rss, bic(rss, normal.n, len(columns), correlation)

    chosen = list(select(total).groups)
    # Candidates that explain the data about as well (BIC within `min_bic_gain` when swapped in) cannot
    # be told apart: shoulder damping and linear drag on the elbow keypoint give the very same joint
    # torques, for example. They are reported together, represented by the one earliest in the order of
    # the effects (and of their candidates).
    classes = []
    for position in range(len(chosen)):
        _, _, bic_best = fit_set(total, chosen)
        members = [chosen[position]]
        for h in range(len(candidates)):
            if h in chosen:
                continue
            trial = chosen[:position] + [h] + chosen[position + 1 :]
            theta_h, _, bic_h = fit_set(total, trial)
            if groups.admissible(theta_h, trial) and bic_h - bic_best < gain:
                members.append(h)
        chosen[position] = min(members)
        classes.append(set(members))
    theta_all, _, bic_all = fit_set(total, chosen)

    # bootstrap over whole runs: inclusion counts a class when any of its members is selected
    runs = A_r.shape[0]
    inclusion = np.zeros(len(chosen))
    draws = []
    for _ in range(bootstrap):
        counts = np.bincount(rng.integers(0, runs, runs), minlength=runs).astype(float)
        normal = Normal(
            np.einsum("r,rcd->cd", counts, A_r), counts @ b_r, float(counts @ c_r), int(counts @ n_r)
        )
        picked = set(select(normal).groups)
        inclusion += [bool(picked & members) for members in classes]
        if chosen:
            draws.append(fit_set(normal, chosen)[0])
    inclusion /= max(bootstrap, 1)
    draws = np.array(draws)

    selected = []
    offset = 0
    for position, g in enumerate(chosen):
        c = candidates[g]
        own = list(groups.columns[g])
        width = len(own)
        theta = theta_all[offset : offset + width] / scale[own]
        samples = draws[:, offset : offset + width] / scale[own][None, :] if len(draws) else None
        offset += width
        others = [h for h in chosen if h != g]
        theta_without, _, bic_without = fit_set(total, others)
        rss_held_with = held.rss(groups.select(chosen)[0], theta_all)
        rss_held_without = held.rss(groups.select(others)[0], theta_without)
        holdout_drop = 1.0 - rss_held_with / rss_held_without if rss_held_without > 0 else 0.0
        sd = float(np.std(samples[:, 0])) if samples is not None and len(samples) > 1 else float("inf")
        t_stat = abs(theta[0]) / sd if sd > 0 else float("inf")
        share = _share(problem, own, theta)
        main = c.parameters(theta)
        values = np.array([c.parameters(v)["value"] for v in samples]) if samples is not None else None
        lo, hi = (
            (float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5)))
            if values is not None and len(values)
            else (float("nan"), float("nan"))
        )
        failed = tuple(
            name
            for name, passed in (
                ("bic_gain", bic_without - bic_all >= gain),
                ("t", t_stat >= criteria.min_t),
                ("inclusion", inclusion[position] >= criteria.min_inclusion),
                ("holdout_drop", holdout_drop >= criteria.min_holdout_drop),
                ("share", share >= criteria.min_share),
            )
            if not passed
        )
        selected.append(
            Detection(
                candidate=c,
                value=main["value"],
                ci=(lo, hi),
                parameters=main,
                bic_gain=float(bic_without - bic_all),
                t=float(t_stat),
                inclusion=float(inclusion[position]),
                holdout_drop=float(holdout_drop),
                share=share,
                alternatives=tuple(sorted(candidates[h].label for h in classes[position] if h != g)),
                round=round_index,
                detected=not failed,
                theta=theta,
                failed=failed,
            )
        )
    selected.sort(key=lambda d: -d.bic_gain)
    summary = Round(
        round=round_index,
        candidates=len(candidates),
        selected=tuple(d.candidate.label for d in selected),
        detected=tuple(d.candidate.label for d in selected if d.detected),
        inclusion={d.candidate.label: d.inclusion for d in selected},
    )
    # as for a detection, what is too small to matter to the motion is not reported
    unphysical = tuple(
        f
        for f in inadmissible(
            total, groups, candidates, chosen, correlation=correlation, min_gain=gain, scale=scale
        )
        if _share(problem, list(groups.columns[f.candidate]), f.theta) >= criteria.min_share
    )
    return Attribution(tuple(selected), summary, groups, unphysical)


def _share(problem: Problem, own: list[int], theta: np.ndarray) -> float:
    """The RMS of the force of columns `own` at coefficients `theta` relative to the inertial forces,
    over the counted equations of the fit runs."""
    kept = problem.kept_fit[..., None]
    force = np.einsum("rtmc,c->rtm", problem.f_fit[..., own], theta) * kept
    inertial = max(float(np.sqrt(np.sum((problem.inertial_fit * kept) ** 2))), 1e-300)
    return float(np.sqrt(np.sum(force**2)) / inertial)
