"""Renumbering keypoints: every estimator and renderer permuted together draws the same images with
the keypoints renumbered, and the assignment finds the order in which keypoints keep the cart-pole's
constraints (the cart at a fixed height, the pole's end at a fixed distance from it)."""

import dataclasses
import itertools
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn
import keyvision

SIZE = 16
ROUNDING = 1e-5  # float32 networks: the same sums in another order
PAIRS = [
    (keyvision.KeypointEstimator, keyvision.Renderer),
    (keyvision.KeypointEstimatorFC, keyvision.RendererFC),
]


@pytest.mark.parametrize(("estimator_cls", "renderer_cls"), PAIRS)
def test_permuted_networks_renumber_the_keypoints_and_draw_the_same(estimator_cls, renderer_cls):
    keys = jax.random.split(jax.random.key(0), 4)
    estimator = estimator_cls(3, width=8, image_size=SIZE, key=keys[0])
    renderer = renderer_cls(3, width=8, image_size=SIZE, key=keys[1])
    images = jax.random.uniform(keys[2], (2, SIZE, SIZE, 3), jnp.float32)
    points = jax.random.uniform(keys[3], (2, 3, 2), jnp.float32, -0.8, 0.8)

    @eqx.filter_jit  # one program for every permutation: the networks are its arguments
    def run(estimator, renderer, points):
        return jax.vmap(estimator)(images), jax.vmap(renderer)(points)

    found, drawn = run(estimator, renderer, points)
    for order in itertools.permutations(range(3)):
        order = list(order)
        # the renumbered renderer, given the renumbered keypoints, draws what the old one drew
        new_found, renumbered = run(estimator.permute(order), renderer.permute(order), points[:, order])
        np.testing.assert_allclose(new_found, found[:, order], atol=ROUNDING)
        np.testing.assert_allclose(renumbered, drawn, atol=ROUNDING)
    with pytest.raises(ValueError, match="permutation of 0..2"):
        estimator.permute([0, 0, 1])
    with pytest.raises(ValueError, match="permutation of 0..2"):
        renderer.permute([0, 1])


def _cartpole_keypoints(runs=6, samples=20, *, cart_first: bool):
    """Keypoints of a cart sliding at height -0.1 and a pole of length 0.5 turning on it."""
    rng = np.random.default_rng(0)
    t = np.arange(samples) * 0.05
    cart = rng.uniform(-0.5, 0.5, (runs, 1)) + 0.3 * np.sin(2 * t + rng.uniform(0, 6, (runs, 1)))
    angle = rng.uniform(-3, 3, (runs, 1)) + 2 * t
    tip = np.stack([cart + 0.5 * np.sin(angle), -0.1 + 0.5 * np.cos(angle)], axis=-1)
    base = np.stack([cart, np.full_like(cart, -0.1)], axis=-1)
    pair = (base, tip) if cart_first else (tip, base)
    return np.concatenate(pair, axis=-1).astype(np.float32)


def _model(scene: str, keypoints: int) -> keyvision.KeyCLD:
    """A small KeyCLD model with KeyCLD's constraints of `scene` and one input."""
    keys = jax.random.split(jax.random.key(1), 3)
    return keyvision.KeyCLD(
        keyvision.KeypointEstimator(keypoints, width=8, image_size=SIZE, key=keys[0]),
        cldyn.keycld_model(2 * keypoints, 1, cldyn.keycld_constraint(scene), key=keys[1], width=8),
        keyvision.Renderer(keypoints, width=8, image_size=SIZE, key=keys[2]),
    )


def test_assign_keypoints_finds_the_order_that_keeps_the_constraints():
    model = _model("cartpole", 2)
    swapped = cldyn.Sequences(_cartpole_keypoints(cart_first=False), None, 0.05)
    renumbered, order = keyvision.assign_keypoints(model, swapped)
    assert order == (1, 0)
    images = jax.random.uniform(jax.random.key(2), (3, SIZE, SIZE, 3), jnp.float32)
    encode = eqx.filter_jit(lambda m, z: m.encode(z))
    expected = encode(model, images)[:, [2, 3, 0, 1]]
    np.testing.assert_allclose(encode(renumbered, images), expected, atol=ROUNDING)
    in_order = cldyn.Sequences(_cartpole_keypoints(cart_first=True), None, 0.05)
    same, order = keyvision.assign_keypoints(model, in_order)
    assert order == (0, 1) and same is model
    # no constraints, nothing to go by
    unconstrained = cldyn.keycld_model(4, 1, None, key=jax.random.key(2), width=8)
    free = eqx.tree_at(lambda m: m.dynamics, model, unconstrained)
    assert keyvision.assign_keypoints(free, swapped)[1] == (0, 1)


class _TwoCorners(keyvision.AbstractKeypointEstimator):
    """A hand-written estimator that does not implement `permute`."""

    num_keypoints: int = 2
    image_size: int = 16

    def __call__(self, image):
        return jnp.array([[-0.5, -0.5], [0.5, 0.5]]) + 0.0 * image.mean()


def test_an_estimator_without_permute_keeps_the_identity_and_refuses_a_renumbering():
    estimator = _TwoCorners()
    assert estimator.permute([0, 1]) is estimator
    with pytest.raises(NotImplementedError, match=r"_TwoCorners does not implement permute.*\[1, 0\]"):
        estimator.permute([1, 0])
    with pytest.raises(ValueError, match="permutation of 0..1"):
        estimator.permute([0, 0])


# -- choosing among autoencoders by their constraints -----------------------------------------------


def _anchor_score(p):
    """The score's closed form for one keypoint `(..., 2)` at a fixed distance from the origin:
    the distance's variance over half the keypoint's total variance (its gradient is a unit vector)."""
    p = np.asarray(p, np.float64).reshape(-1, 2)
    return np.hypot(p[:, 0], p[:, 1]).var() / (p.var(axis=0).sum() / 2)


def _cartpole_score(x):
    """The closed form for the cart-pole's keypoints `(..., 4)`: the cart's height over half the cart's
    total variance, and the pole's length over half the sum of both keypoints' (unit gradients), averaged."""
    x = np.asarray(x, np.float64).reshape(-1, 4)
    cart, tip = x[:, :2], x[:, 2:]
    height = cart[:, 1].var() / (cart.var(axis=0).sum() / 2)
    length = np.hypot(*(tip - cart).T).var() / ((cart.var(axis=0).sum() + tip.var(axis=0).sum()) / 2)
    return (height + length) / 2


def test_constraint_score_is_zero_for_rigid_keypoints_and_the_spread_against_the_motion_otherwise():
    model = _model("cartpole", 2)
    # the cart at a fixed height and the pole's end at a fixed distance, in either numbering
    for cart_first in (True, False):
        rigid = cldyn.Sequences(_cartpole_keypoints(cart_first=cart_first), None, 0.05)
        assert keyvision.constraint_score(model, rigid) < 1e-10
    # the second keypoint slides along the pole, at 0.6 to 1.0 of it: the cart's height keeps, and
    # the length's variance over every frame is set against the two keypoints' motion
    x = _cartpole_keypoints(cart_first=True).astype(np.float64)
    rng = np.random.default_rng(5)
    fraction = rng.uniform(0.6, 1.0, x.shape[:2])
    x[..., 2:] = x[..., :2] + fraction[..., None] * (x[..., 2:] - x[..., :2])
    sliding = cldyn.Sequences(x.astype(np.float32), None, 0.05)
    assert keyvision.constraint_score(model, sliding) == pytest.approx(_cartpole_score(x), rel=1e-4)
    # the picture's scale changes nothing
    scaled = cldyn.Sequences((3 * x).astype(np.float32), None, 0.05)
    assert keyvision.constraint_score(model, scaled) == pytest.approx(_cartpole_score(x), rel=1e-4)
    # the cart off its rail adds its height's variance against the cart's motion
    x[..., 1] += 0.05 * rng.standard_normal(x.shape[:2])
    off = cldyn.Sequences(x.astype(np.float32), None, 0.05)
    assert keyvision.constraint_score(model, off) == pytest.approx(_cartpole_score(x), rel=1e-4)
    unconstrained = cldyn.keycld_model(4, 1, None, key=jax.random.key(2), width=8)
    free = eqx.tree_at(lambda m: m.dynamics, model, unconstrained)
    with pytest.raises(ValueError, match="needs dynamics with constraints"):
        keyvision.constraint_score(free, sliding)
    with pytest.raises(ValueError, match="keypoints of 2 coordinates for a model of 2 keypoints"):
        keyvision.constraint_score(model, cldyn.Sequences(x[..., :2].astype(np.float32), None, 0.05))


def test_a_keypoint_that_stands_still_scores_as_badly_as_one_that_wanders():
    # a pendulum's keypoint: on the bob (radius 0.6, swinging) or standing at one place 0.6 from the
    # pivot, each with the same jitter. Both keep their distance from the pivot to the jitter's
    # size, so the distance's spread over its mean square cannot tell them apart (2.8e-4 each);
    # against their motion, the one on the bob scores near 0 and the one standing still near 1,
    # worse than a keypoint that wanders over the picture (0.24)
    model = _model("pendulum", 1)
    rng = np.random.default_rng(7)
    angle = rng.uniform(-2.5, 2.5, (40, 50))
    bob = 0.6 * np.stack([np.sin(angle), -np.cos(angle)], axis=-1) + 0.01 * rng.standard_normal((40, 50, 2))
    still = np.array([0.6 * np.sin(0.7), -0.6 * np.cos(0.7)]) + 0.01 * rng.standard_normal((40, 50, 2))
    wander = rng.uniform(-0.8, 0.8, (40, 50, 2))
    scores = {}
    for name, p in (("bob", bob), ("still", still), ("wander", wander)):
        scores[name] = keyvision.constraint_score(model, cldyn.Sequences(p.astype(np.float32), None, 0.05))
        assert scores[name] == pytest.approx(_anchor_score(p), rel=1e-3)
    assert scores["bob"] < 0.01 < 0.1 < scores["wander"] < 0.8 < scores["still"] < 1.2
    # the spread over the mean square, the same for both to within 10%
    distances = [np.hypot(*p.reshape(-1, 2).T) for p in (bob, still)]
    relative = [d.var() / d.mean() ** 2 for d in distances]
    assert relative[1] == pytest.approx(relative[0], rel=0.1)


class _Centroid(keyvision.AbstractKeypointEstimator):
    """A hand-written estimator: the centroid of the bright pixels, its height scaled by `squash`
    (1: the disc's centre; below 1 a point that no longer keeps its distance from the pivot)."""

    squash: float
    num_keypoints: int = 1
    image_size: int = SIZE

    def __call__(self, image):
        weight = jnp.mean(image, axis=-1) - 0.1
        centres = ((2 * jnp.arange(SIZE) + 1) / SIZE - 1).astype(image.dtype)
        x = jnp.sum(weight * centres[None, :]) / jnp.sum(weight)
        y = jnp.sum(weight * -centres[:, None]) / jnp.sum(weight)
        return jnp.stack([x, jnp.asarray(self.squash, image.dtype) * y])[None]


def _disc_frames(runs=4, samples=6, radius=0.6):
    """uint8 frames of a disc at `radius` from the image centre at random angles (a pendulum's bob)."""
    rng = np.random.default_rng(3)
    angles = rng.uniform(-np.pi, np.pi, (runs, samples))
    bob = radius * np.stack([np.sin(angles), -np.cos(angles)], axis=-1)
    centres = (2 * np.arange(SIZE) + 1) / SIZE - 1
    xs, ys = np.meshgrid(centres, -centres)
    distance = np.hypot(xs - bob[..., 0, None, None], ys - bob[..., 1, None, None])
    cover = np.clip((0.2 - distance) * SIZE / 2 + 0.5, 0, 1)
    images = 0.1 + 0.8 * cover[..., None] * np.ones(3)
    frames = np.round(255 * images).astype(np.uint8)
    return keyvision.ImageSequences(frames, np.zeros((runs, samples, 1), np.float32), 0.1), bob


def test_training_continues_the_candidate_whose_keypoints_keep_the_constraints(tmp_path, monkeypatch):
    # two candidates with the same renderer and dynamics: the first's keypoint is the disc's centre
    # squashed to half its height (its distance from the pivot swings), the second's the centre. The
    # trials train only the renderers (these estimators have no parameters); the second is chosen,
    # and the scores are their closed forms (numpy on the true positions, within the centroid's
    # error of a few thousandths)
    data, bob = _disc_frames()
    keys = jax.random.split(jax.random.key(0), 2)
    dynamics = cldyn.keycld_model(2, 1, cldyn.keycld_constraint("pendulum"), key=keys[0], width=8)
    renderer = keyvision.Renderer(1, width=8, image_size=SIZE, key=keys[1])
    float32 = eqx.filter_jit(
        lambda tree: jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, tree)
    )
    dynamics, renderer = float32(dynamics), float32(renderer)
    candidates = [keyvision.KeyCLD(_Centroid(squash), dynamics, renderer) for squash in (0.5, 1.0)]
    schedule = keyvision.Schedule(
        candidates=2, candidate_steps=2, autoencoder_steps=2, autoencoder_batch=4, dynamics_steps=0,
        joint_steps=0, refit_steps=0, heatmap_weight=0.0, log_every=1,
    )
    meter = _Recorder()
    result = keyvision.train(candidates, data, key=jax.random.key(1), schedule=schedule, out=tmp_path,
                             progress_meter=meter)
    assert list(result.stages) == ["candidate-1", "candidate-2", "autoencoder"]
    assert meter.lines[-2:] == [("scoring candidates", 1), ("scoring candidates", 2)]
    assert result.candidates["chosen"] == "candidate-2"
    good, bad = result.candidates["scores"][1], result.candidates["scores"][0]
    assert bad == pytest.approx(_anchor_score(bob * [1.0, 0.5]), rel=0.05)
    assert good < 0.01 * bad
    record = json.loads((tmp_path / "candidates.json").read_text())
    assert record["chosen"] == "candidate-2" and record["scores"] == result.candidates["scores"]
    assert isinstance(result.model.estimator, _Centroid) and result.model.estimator.squash == 1.0
    # resumed, the finished trials are read back and the recorded choice is kept: nothing is encoded
    monkeypatch.setattr(keyvision._assign, "encode_sequences", _no_encoding)
    resumed = keyvision.train(candidates, data, key=jax.random.key(1), schedule=schedule, out=tmp_path,
                              resume=True)
    assert resumed.candidates == result.candidates
    # a damaged record after stage (a) started from it is named, and nothing is overwritten
    (tmp_path / "candidates.json").write_text("{")
    checkpoint = (tmp_path / "checkpoint-autoencoder.eqx").read_bytes()
    with pytest.raises(cldyn.CheckpointError, match="candidates.json: not a choice among the candidates"):
        keyvision.train(candidates, data, key=jax.random.key(1), schedule=schedule, out=tmp_path, resume=True)
    assert (tmp_path / "checkpoint-autoencoder.eqx").read_bytes() == checkpoint
    # scored on at most 2 of 5 runs: every 3rd (runs 0 and 3) is encoded, and the score is the closed
    # form on those runs
    monkeypatch.undo()
    five, bob = _disc_frames(runs=5)
    encoded = []

    def spy(model, data):
        encoded.append(np.asarray(data.frames))
        return keyvision._evaluate.encode_sequences(model, data)

    monkeypatch.setattr(keyvision._assign, "encode_sequences", spy)
    few = dataclasses.replace(schedule, candidate_runs=2)
    subset = keyvision.train(candidates, five, key=jax.random.key(1), schedule=few).candidates
    assert len(encoded) == 2 and all(np.array_equal(e, np.asarray(five.frames)[[0, 3]]) for e in encoded)
    assert subset["runs"] == 2 and result.candidates["runs"] == 4
    assert subset["scores"][0] == pytest.approx(_anchor_score(bob[::3] * [1.0, 0.5]), rel=0.05)
    with pytest.raises(ValueError, match="candidate_runs"):
        keyvision.Schedule(candidate_runs=0)
    # the number of models must match the schedule, and a model without constraints has nothing to go by
    with pytest.raises(ValueError, match="1 models given for Schedule.candidates = 2"):
        keyvision.train(candidates[0], data, key=jax.random.key(1), schedule=schedule)
    unconstrained = cldyn.keycld_model(2, 1, None, key=keys[0], width=8)
    free = [eqx.tree_at(lambda m: m.dynamics, c, unconstrained) for c in candidates]
    refused = r"choosing among candidates \(Schedule.candidates = 2\) needs dynamics with constraints"
    with pytest.raises(ValueError, match=refused):
        keyvision.train(free, data, key=jax.random.key(1), schedule=schedule)
    with pytest.raises(TypeError, match="loop must be a cldyn step loop .* got 'compiled'"):
        keyvision.train(candidates, data, key=jax.random.key(1), schedule=schedule, loop="compiled")


class _Recorder(cldyn.AbstractProgressMeter):
    """Keeps every update of the scoring of candidates: (description, done)."""

    lines: list = eqx.field(default_factory=list)

    def start(self, total, *, initial=0, desc="", unit="step"):
        return desc

    def update(self, state, done, info=None):
        if state == "scoring candidates":
            self.lines.append((state, done))
        return state

    def close(self, state):
        del state


def _no_encoding(*_):
    raise AssertionError("the frames were encoded again")
