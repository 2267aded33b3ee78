"""Spatial softmax (eq. 8), Gaussian maps (eq. 9) and the image frame, against closed forms."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import keyvision

SIZE = 64
FLOAT32_TOL = 2e-6  # a few float32 ulps of numbers of order 1
# The mean of a Gaussian sampled at 3 pixels per sigma: aliasing ~exp(-2 pi^2 9), float32 sums dominate.
ALIASING_TOL = 1e-5
OFFSET_TOL = 1e-3  # logits rounded to float32 spacing at 1e3 (6e-5)


def _centre(row, col, height=SIZE, width=SIZE):
    """The image-frame centre of pixel (row, col), from the definition: cells 2/W wide, row 0 on top."""
    return np.array([-1 + (col + 0.5) * 2 / width, 1 - (row + 0.5) * 2 / height])


def test_pixel_grid_corners_and_orientation():
    grid = np.asarray(keyvision.pixel_grid(4, 8))
    assert grid.shape == (4, 8, 2)
    np.testing.assert_allclose(grid[0, 0], [-1 + 1 / 8, 1 - 1 / 4], atol=FLOAT32_TOL)  # top left
    np.testing.assert_allclose(grid[3, 7], [1 - 1 / 8, -1 + 1 / 4], atol=FLOAT32_TOL)  # bottom right
    assert np.all(np.diff(grid[:, 0, 1]) < 0)  # y decreases down the rows: y points up
    assert np.all(np.diff(grid[0, :, 0]) > 0)  # x increases along the columns


def test_pixel_and_frame_conventions_agree_both_ways():
    rows, cols = np.meshgrid(np.arange(5), np.arange(7), indexing="ij")
    pixels = np.stack([rows, cols], axis=-1).astype(np.float64)
    points = np.asarray(keyvision.pixel_to_frame(pixels, 5, 7))
    np.testing.assert_allclose(points, np.asarray(keyvision.pixel_grid(5, 7, dtype=jnp.float64)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(keyvision.frame_to_pixel(points, 5, 7)), pixels, atol=1e-12)
    corners = np.asarray(keyvision.frame_to_pixel(np.array([[-1.0, 1.0], [1.0, -1.0]]), 5, 7))
    np.testing.assert_allclose(corners, [[-0.5, -0.5], [4.5, 6.5]], atol=1e-12)


@pytest.mark.parametrize("row, col", [(10, 40), (0, 0), (63, 17)])
def test_single_hot_pixel_gives_its_centre(row, col):
    logits = jnp.zeros((1, SIZE, SIZE), jnp.float32).at[0, row, col].set(1e4)
    keypoint = np.asarray(keyvision.spatial_softmax(logits))[0]
    np.testing.assert_allclose(keypoint, _centre(row, col), atol=FLOAT32_TOL)


@pytest.mark.parametrize("row, col", [(20.0, 40.0), (20.5, 33.5), (30.25, 12.75)])
def test_symmetric_blob_gives_its_centre(row, col):
    """A Gaussian blob of logits about any point (pixel centre, pixel corner or in between)."""
    rows, cols = np.meshgrid(np.arange(SIZE), np.arange(SIZE), indexing="ij")
    spread = 2.0  # pixels
    logits = -((rows - row) ** 2 + (cols - col) ** 2) / (2 * spread**2)
    keypoint = np.asarray(keyvision.spatial_softmax(jnp.asarray(logits[None], jnp.float32)))[0]
    np.testing.assert_allclose(keypoint, _centre(row, col), atol=ALIASING_TOL)


def test_huge_logits_stay_finite_and_shift_invariant():
    key1, key2 = jax.random.split(jax.random.key(0))
    logits = jax.random.normal(key1, (3, SIZE, SIZE), jnp.float32)
    reference = np.asarray(keyvision.spatial_softmax(logits))
    shifted = np.asarray(keyvision.spatial_softmax(logits + 1e3))  # exp(1e3) overflows float32
    assert np.all(np.isfinite(shifted))
    np.testing.assert_allclose(shifted, reference, atol=OFFSET_TOL)
    huge = jnp.where(jax.random.uniform(key2, (3, SIZE, SIZE)) > 0.5, 3e38, -3e38).astype(jnp.float32)
    points = np.asarray(keyvision.spatial_softmax(huge))
    assert np.all(np.isfinite(points)) and np.all(np.abs(points) <= 1)
    gradient = jax.grad(lambda z: keyvision.spatial_softmax(z).sum())(logits * 1e6)
    assert np.all(np.isfinite(np.asarray(gradient)))


def test_gaussian_maps_peak_and_closed_form_offsets():
    sigma = 0.1
    point = _centre(20, 30)
    maps = np.asarray(
        keyvision.gaussian_maps(jnp.asarray(point[None], jnp.float32), SIZE, SIZE, sigma=sigma)
    )[0]
    assert maps.shape == (SIZE, SIZE)
    assert np.unravel_index(np.argmax(maps), maps.shape) == (20, 30)
    np.testing.assert_allclose(maps[20, 30], 1.0, atol=FLOAT32_TOL)
    step = 2 / SIZE
    for drow, dcol in [(0, 1), (1, 0), (-2, 3), (5, -4)]:
        expected = math.exp(-((drow * step) ** 2 + (dcol * step) ** 2) / (2 * sigma**2))
        np.testing.assert_allclose(maps[20 + drow, 30 + dcol], expected, rtol=1e-5)


def test_softmax_of_log_gaussian_map_returns_the_keypoint():
    """eq. 8 inverts eq. 9: the expected position under a Gaussian blob is its centre."""
    points = jnp.array([[0.123, -0.456], [-0.3, 0.21]], jnp.float32)
    maps = keyvision.gaussian_maps(points, SIZE, SIZE, sigma=0.1)
    recovered = keyvision.spatial_softmax(jnp.log(maps))
    np.testing.assert_allclose(np.asarray(recovered), np.asarray(points), atol=ALIASING_TOL)


# -- keypoints drawn on frames ---------------------------------------------------------------------


def test_draw_keypoints_marks_the_pixel_of_each_point_and_moves_with_it():
    frames = np.zeros((2, 16, 16, 3))
    # keypoint 0 at the centre of pixel (row 3, col 10); keypoint 1 at the centre of pixel (12, 1)
    points = np.asarray(keyvision.pixel_to_frame(np.array([[3.0, 10.0], [12.0, 1.0]]), 16, 16)).reshape(-1)
    marked = keyvision.draw_keypoints(frames, np.stack([points, points + np.array([2 / 16, 0, 0, -4 / 16])]),
                                      radius=0, colors=[(1, 0, 0), (0, 0, 1)])
    assert marked.dtype == np.uint8 and marked.shape == frames.shape
    assert np.argwhere(marked[0, ..., 0] == 255).tolist() == [[3, 10]]
    assert np.argwhere(marked[0, ..., 2] == 255).tolist() == [[12, 1]]
    assert marked[0].sum() == 2 * 255
    # one pixel right (x + 2/16) and two pixels down (y - 4/16) in the second frame
    assert np.argwhere(marked[1, ..., 0] == 255).tolist() == [[3, 11]]
    assert np.argwhere(marked[1, ..., 2] == 255).tolist() == [[14, 1]]
    # a radius of 1 paints 3 x 3 pixels, clipped at the border; a point outside the image paints nothing
    wide = keyvision.draw_keypoints(frames[0], np.array([-1.0, 1.0, 5.0, 0.0]), radius=1)
    assert int((wide.sum(axis=-1) > 0).sum()) == 4
    with pytest.raises(ValueError, match="one RGB colour per keypoint"):
        keyvision.draw_keypoints(frames[0], points, colors=[(1, 0, 0)])
    with pytest.raises(ValueError, match=r"\(\.\.\., 2K\)"):
        keyvision.draw_keypoints(frames[0], points[:3])
