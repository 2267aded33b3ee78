"""Progress meters: how a long job (a fit, a recording, an identification) reports how far it is.

Like diffrax's `progress_meter`, the meter is an option object passed to the job. The job calls it
on the host, at points it chooses (a fit at its log points, never inside compiled code), so a meter
costs nothing between those points. The protocol is functional, as Equinox modules are immutable:
`start` returns a state, `update` takes and returns it, `close` ends it.
"""

import abc
import dataclasses
import io
import math
import sys
import time
from collections.abc import Mapping
from typing import Any

import equinox as eqx

from ._misc import check_positive, optional_import

Info = Mapping[str, float | int | str | None]


class AbstractProgressMeter(eqx.Module):
    """How a job reports its progress: `state = meter.start(total)`, then
    `state = meter.update(state, done, info)` as units complete, and `meter.close(state)` at the end.

    `done` counts units (steps of a fit, runs of a recording) and only grows; `info` holds a few
    named figures to show beside it (e.g. `{"loss": 1.2e-3}`; `None` values are skipped). A job
    calls `close` also when it stops early (an error or Ctrl-C).

    !!! example

        ```python
        meter = cldyn.TextProgressMeter()
        state = meter.start(1000, desc="fit", unit="step")
        for done in range(100, 1001, 100):
            state = meter.update(state, done, {"loss": 0.1})
        meter.close(state)
        ```
    """

    @abc.abstractmethod
    def start(self, total: int, *, initial: int = 0, desc: str = "", unit: str = "step") -> Any:
        """Begin a job of `total` units of which `initial` are already done (a resumed fit).

        **Returns:** the meter's state, to pass to `update` and `close`.
        """

    @abc.abstractmethod
    def update(self, state: Any, done: int, info: Info | None = None) -> Any:
        """Report that `done` units of the total are complete.

        **Returns:** the new state.
        """

    @abc.abstractmethod
    def close(self, state: Any) -> None:
        """End the report (the job finished or stopped)."""


class NoProgressMeter(AbstractProgressMeter):
    """Report nothing: the library's default.

    !!! example

        ```python
        cldyn.fit(model, data, loss=loss, steps=100, key=key, progress_meter=cldyn.NoProgressMeter())
        ```
    """

    def start(self, total: int, *, initial: int = 0, desc: str = "", unit: str = "step") -> None:
        del total, initial, desc, unit

    def update(self, state: None, done: int, info: Info | None = None) -> None:
        del state, done, info

    def close(self, state: None) -> None:
        del state


def _format_value(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _format_info(info: Info | None) -> str:
    if not info:
        return ""
    return "".join(f" {name}={_format_value(value)}" for name, value in info.items() if value is not None)


def _format_seconds(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}"


@dataclasses.dataclass(frozen=True)
class _TextState:
    total: int
    desc: str
    unit: str
    started: float
    first: tuple[float, int] | None  # (time, done) of the first update: the rate leaves out compilation
    printed: float  # when the last line was printed; -inf before the first
    pending: str | None  # the latest line not printed yet (rate-limited), printed by close
    done: int


class TextProgressMeter(AbstractProgressMeter):
    """Plain lines of text (to standard error by default), at most one every `interval` seconds.

    Each line shows the units done, the percentage, the rate (units per second, measured from the
    first update on, so that compilation does not count), the estimated time to finish and the
    figures of `info`, e.g.
    `fit: 1200/6000 steps (20%), 310.5 steps/s, ETA 0:00:15, loss=0.0123`.
    The first and the final update are always printed; suited to logs and batch jobs, where a
    redrawn bar is noise.

    **Arguments:**

    - `interval`: the least number of seconds between two lines (`0` prints every update).
    - `file`: where to write; `sys.stderr` at the time of writing by default.

    !!! example

        ```python
        result = cldyn.fit(model, data, loss=cldyn.Collocation(), steps=5000, key=key,
                           progress_meter=cldyn.TextProgressMeter(interval=30.0))
        ```
    """

    interval: float | int = eqx.field(static=True, default=10.0)
    file: io.TextIOBase | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        check_positive("TextProgressMeter: interval", self.interval, allow_zero=True)

    def _write(self, line: str) -> None:
        stream = sys.stderr if self.file is None else self.file
        print(line, file=stream, flush=True)

    def start(self, total: int, *, initial: int = 0, desc: str = "", unit: str = "step") -> _TextState:
        return _TextState(int(total), desc, unit, time.perf_counter(), None, -math.inf, None, int(initial))

    def update(self, state: _TextState, done: int, info: Info | None = None) -> _TextState:
        now = time.perf_counter()
        first = state.first
        if first is None or done <= first[1]:
            first = (now, done)
            rate = math.nan
        else:
            rate = (done - first[1]) / max(now - first[0], 1e-9)
        remaining = (state.total - done) / rate if rate > 0 else math.nan
        units = state.unit + ("s" if state.total != 1 else "")
        percent = 100.0 * done / state.total if state.total > 0 else 100.0
        line = f"{state.desc + ': ' if state.desc else ''}{done}/{state.total} {units} ({percent:.0f}%)"
        if math.isfinite(rate):
            line += f", {rate:.4g} {state.unit}s/s, ETA {_format_seconds(remaining)}"
        line += _format_info(info)
        if now - state.printed >= self.interval or done >= state.total:
            self._write(line)
            return dataclasses.replace(state, first=first, printed=now, pending=None, done=done)
        return dataclasses.replace(state, first=first, pending=line, done=done)

    def close(self, state: _TextState) -> None:
        if state.pending is not None:
            self._write(state.pending)
        elapsed = _format_seconds(time.perf_counter() - state.started)
        prefix = f"{state.desc}: " if state.desc else ""
        self._write(f"{prefix}ended at {state.done}/{state.total} {state.unit}s after {elapsed}")


class TqdmProgressMeter(AbstractProgressMeter):
    """A tqdm progress bar (needs the optional package `tqdm`: `pip install 'cldyn[vision]'`).

    The bar shows the units done, the rate, the estimated time to finish and the figures of `info`
    as its postfix. tqdm is imported when the bar starts, not when cldyn is imported.

    !!! example

        ```python
        result = cldyn.fit(model, data, loss=cldyn.Collocation(), steps=5000, key=key,
                           progress_meter=cldyn.TqdmProgressMeter())
        ```
    """

    def start(self, total: int, *, initial: int = 0, desc: str = "", unit: str = "step") -> Any:
        tqdm = optional_import("tqdm.auto", purpose="TqdmProgressMeter").tqdm
        return tqdm(total=total, initial=initial, desc=desc or None, unit=unit, dynamic_ncols=True)

    def update(self, state: Any, done: int, info: Info | None = None) -> Any:
        if done > state.n:
            state.update(done - state.n)
        if info:
            shown = {name: _format_value(value) for name, value in info.items() if value is not None}
            state.set_postfix(shown, refresh=True)
        return state

    def close(self, state: Any) -> None:
        state.close()
