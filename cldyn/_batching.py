"""How `fit` draws a batch from its training data at every step: whole runs, or windows of runs.

The data are any PyTree whose arrays lead with the run axis (a `Sequences`, or frames and controls
of a vision model); the batch has the same structure. Draws are functions of a key, traced inside
the compiled training loop, so a resumed fit draws the same batches as an uninterrupted one.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray, PyTree

from ._misc import check_positive


def _arrays(data) -> list:
    return [a for a in jax.tree.leaves(data) if eqx.is_array(a)]


def num_runs(data) -> int:
    """The length of the run axis that every array of `data` leads with; a `ValueError` otherwise."""
    arrays = _arrays(data)
    if not arrays:
        raise ValueError("fit: the data hold no arrays")
    shapes = {tuple(a.shape[:1]) for a in arrays}
    if len(shapes) != 1 or () in shapes:
        shown = sorted({tuple(a.shape) for a in arrays})
        raise ValueError(f"fit: every array of the data must lead with the same run axis; shapes {shown}")
    return arrays[0].shape[0]


class AbstractBatching(eqx.Module):
    """How `fit` draws a batch of `batch_size` examples from the training data at each step.

    `check(data)` refuses data the draw cannot serve (before any work); `draw(data, key)` returns a
    batch of the same PyTree structure, with leading axis `batch_size`.
    """

    batch_size: eqx.AbstractVar[int]

    @abc.abstractmethod
    def check(self, data: PyTree) -> None:
        """Raise a `ValueError` that says why, if batches cannot be drawn from `data`."""

    @abc.abstractmethod
    def draw(self, data: PyTree, key: PRNGKeyArray) -> PyTree:
        """A batch from `data` with the randomness of `key` (traced: works under `jax.jit`)."""


class Runs(AbstractBatching):
    """Batches of whole runs, drawn without replacement (a random permutation when `batch_size`
    is the number of runs).

    **Arguments:**

    - `batch_size`: runs per batch, at most the number of training runs.

    !!! example

        ```python
        result = cldyn.fit(model, train, loss=cldyn.Collocation(), steps=6000, key=key,
                           batching=cldyn.Runs(32))
        ```
    """

    batch_size: int = eqx.field(static=True)

    def __check_init__(self):
        check_positive("Runs: batch_size", self.batch_size, integer=True)

    def check(self, data: PyTree) -> None:
        runs = num_runs(data)
        if self.batch_size > runs:
            raise ValueError(
                f"fit: batch size {self.batch_size} is larger than the {runs} training runs; "
                f"use Runs({runs}) or fewer"
            )

    def draw(self, data: PyTree, key: PRNGKeyArray) -> PyTree:
        runs = num_runs(data)
        if self.batch_size >= runs:
            indices = jax.random.permutation(key, runs)
        else:
            indices = jax.random.choice(key, runs, (self.batch_size,), replace=False)
        return jax.tree.map(lambda a: a[indices], data)


class Windows(AbstractBatching):
    """Batches of windows: `length` consecutive samples of a random run, from a random start.

    Every array of the data leads with `(runs, T)`; the batch's arrays lead with
    `(batch_size, length)`. Runs and starts are drawn independently and uniformly (with
    replacement), so `batch_size` may exceed the number of runs. Short windows of long runs are how
    KeyCLD is trained from images (8-12 frames of 50-frame runs): each step sees more runs for the
    same cost.

    **Arguments:**

    - `batch_size`: windows per batch.
    - `length`: samples per window, at most `T`.

    !!! example

        ```python
        result = cldyn.fit(model, train, loss=cldyn.Collocation(), steps=6000, key=key,
                           batching=cldyn.Windows(64, length=10))
        ```
    """

    batch_size: int = eqx.field(static=True)
    length: int = eqx.field(static=True)

    def __check_init__(self):
        check_positive("Windows: batch_size", self.batch_size, integer=True)
        check_positive("Windows: length", self.length, integer=True)

    def check(self, data: PyTree) -> None:
        num_runs(data)
        samples = {a.shape[1] if a.ndim > 1 else None for a in _arrays(data)}
        if len(samples) != 1 or None in samples:
            shown = sorted({tuple(a.shape) for a in _arrays(data)})
            raise ValueError(
                f"fit: Windows needs every array of the data to lead with (runs, T); shapes {shown}"
            )
        (total,) = samples
        if self.length > total:
            raise ValueError(f"fit: windows of {self.length} samples do not fit in runs of {total} samples")

    def draw(self, data: PyTree, key: PRNGKeyArray) -> PyTree:
        runs = num_runs(data)
        total = _arrays(data)[0].shape[1]
        run_key, start_key = jax.random.split(key)
        run = jax.random.randint(run_key, (self.batch_size, 1), 0, runs)
        start = jax.random.randint(start_key, (self.batch_size, 1), 0, total - self.length + 1)
        samples = start + jnp.arange(self.length)[None, :]
        return jax.tree.map(lambda a: a[run, samples], data)
