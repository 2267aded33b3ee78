"""Joint limits, which the model does not express: the samples where a joint is at a limit are left
out of the equations, and rollouts end at the first contact, rather than attributing the limit's force
to an effect the model can express (a spring, say)."""

from collections.abc import Mapping

import numpy as np

# a joint within this fraction of its range (plus three times its noise) of a limit is at the limit
_RANGE_FRACTION = 0.005


def limit_contacts(
    q: np.ndarray,
    joint_names: tuple[str, ...],
    joint_limits: Mapping[str, tuple[float, float]],
    joint_noise: list[float],
    dilation: int,
) -> tuple[np.ndarray, list[str]]:
    """The kept samples at which a joint is at one of its limits, widened by `dilation` samples on
    each side (smoothing spreads a contact over half a window), and a note per joint that reaches one.

    **Arguments:**

    - `q`: the joint coordinates `(runs, T', m)` at the kept samples.
    - `joint_names`: their names; `joint_limits`: name -> `(low, high)` for the limited joints.
    - `joint_noise`: each joint's noise (position noise times `|grad q|`).
    - `dilation`: kept samples to widen each contact by.

    **Returns:** `(excluded (runs, T') bool, notes)`.
    """
    unknown = sorted(set(joint_limits) - set(joint_names))
    if unknown:
        raise ValueError(
            f"joint_limits names joints the model lacks: {unknown}; its joints are {list(joint_names)}"
        )
    runs, samples = q.shape[:2]
    contact = np.zeros((runs, samples), dtype=bool)
    notes = []
    for j, name in enumerate(joint_names):
        if name not in joint_limits:
            continue
        low, high = (float(v) for v in joint_limits[name])
        if not low < high:
            raise ValueError(f"joint_limits[{name!r}]: need low < high, got ({low}, {high})")
        tolerance = 3.0 * joint_noise[j] + _RANGE_FRACTION * (high - low)
        at = (q[..., j] <= low + tolerance) | (q[..., j] >= high - tolerance)
        if at.any():
            notes.append(
                f"joint {name!r} reaches its limits [{low:.4g}, {high:.4g}] in "
                f"{int(at.any(axis=1).sum())} of {runs} runs"
            )
        contact |= at
    if dilation > 0 and contact.any():
        widened = contact.copy()
        for shift in range(1, dilation + 1):
            widened[:, shift:] |= contact[:, :-shift]
            widened[:, :-shift] |= contact[:, shift:]
        contact = widened
    return contact, notes
