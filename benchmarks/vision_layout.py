"""Which convolution layout trains keyvision's networks faster on this machine?

Times one forward and backward pass (images/s) of the paper's autoencoder (appendix A.4: the U-Net
keypoint estimator, spatial softmax, Gaussian maps and the U-Net renderer, mean squared
reconstruction error) in float32, for two layouts of the same network:

- `channels_first`: keyvision's own modules (`equinox.nn.Conv2d`, `(C, H, W)` per example, vmapped);
- `channels_last`: the same architecture written here with `lax.conv_general_dilated` on `NHWC`
  batches.

A float32 matrix product gives the machine's reference speed in the same run. Prints one JSON
object and writes `benchmarks/results/vision_layout.json`.

    python benchmarks/vision_layout.py [--quick]
"""

import argparse
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import machine, write

import keyvision

NUM_KEYPOINTS = 2
SIGMA = 0.1


# -- channels-last reference implementation --------------------------------------------------------


def _conv_init(key, cin, cout):
    bound = 1 / np.sqrt(9 * cin)
    wkey, bkey = jax.random.split(key)
    return {
        "w": jax.random.uniform(wkey, (3, 3, cin, cout), jnp.float32, -bound, bound),
        "b": jax.random.uniform(bkey, (cout,), jnp.float32, -bound, bound),
    }


def _conv(p, x):
    y = jax.lax.conv_general_dilated(x, p["w"], (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y + p["b"]


def _block_init(key, cin, cout):
    return {**_conv_init(key, cin, cout), "scale": jnp.ones(cout), "shift": jnp.zeros(cout)}


def _block(p, x):
    y = _conv(p, x)
    n, h, w, c = y.shape
    groups = min(8, c)
    g = y.reshape(n, h, w, groups, c // groups)
    mean = g.mean(axis=(1, 2, 4), keepdims=True)
    var = g.var(axis=(1, 2, 4), keepdims=True)
    y = ((g - mean) * jax.lax.rsqrt(var + 1e-5)).reshape(n, h, w, c)
    return jax.nn.relu(y * p["scale"] + p["shift"])


def _pool(x):
    n, h, w, c = x.shape
    return x.reshape(n, h // 2, 2, w // 2, 2, c).max(axis=(2, 4))


def _up(x):
    return jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)


def _unet_init(key, cin, cout, width):
    keys = jax.random.split(key, 6)
    return {
        "d1": _block_init(keys[0], cin, width),
        "d2": _block_init(keys[1], width, 2 * width),
        "b": _block_init(keys[2], 2 * width, 4 * width),
        "u2": _block_init(keys[3], 6 * width, 2 * width),
        "u1": _block_init(keys[4], 3 * width, width),
        "head": _conv_init(keys[5], width, cout),
    }


def _unet(p, x):
    x1 = _block(p["d1"], x)
    x2 = _block(p["d2"], _pool(x1))
    x3 = _block(p["b"], _pool(x2))
    x4 = _block(p["u2"], jnp.concatenate([_up(x3), x2], axis=-1))
    x5 = _block(p["u1"], jnp.concatenate([_up(x4), x1], axis=-1))
    return _conv(p["head"], x5)


def _channels_last(width, size, key):
    ekey, rkey, ckey = jax.random.split(key, 3)
    constant = max(1, width - NUM_KEYPOINTS)
    params = {
        "estimator": _unet_init(ekey, 3, NUM_KEYPOINTS, width),
        "renderer": _unet_init(rkey, constant + NUM_KEYPOINTS, 3, width),
        "constant": 0.01 * jax.random.normal(ckey, (size, size, constant)),
    }

    def loss(params, images):
        n = images.shape[0]
        logits = _unet(params["estimator"], images)  # (N, H, W, K)
        keypoints = jax.vmap(keyvision.spatial_softmax)(jnp.moveaxis(logits, -1, 1))
        maps = jax.vmap(lambda k: keyvision.gaussian_maps(k, size, size, sigma=SIGMA))(keypoints)
        inputs = jnp.concatenate(
            [jnp.broadcast_to(params["constant"], (n, size, size, constant)), jnp.moveaxis(maps, 1, -1)], -1
        )
        out = jax.nn.sigmoid(_unet(params["renderer"], inputs))
        return jnp.mean((out - images) ** 2)

    return params, loss


def _channels_first(width, size, key):
    ekey, rkey = jax.random.split(key)
    params = (
        keyvision.KeypointEstimator(NUM_KEYPOINTS, width=width, image_size=size, key=ekey),
        keyvision.Renderer(NUM_KEYPOINTS, width=width, image_size=size, sigma=SIGMA, key=rkey),
    )

    def loss(params, images):
        estimator, renderer = params
        out = jax.vmap(lambda image: renderer(estimator(image)))(images)
        return jnp.mean((out - images) ** 2)

    return params, loss


LAYOUTS = {"channels_first": _channels_first, "channels_last": _channels_last}


def _time(width, size, batch, repeats) -> list[dict]:
    """Both layouts of one configuration, their timed calls interleaved (A, B, A, B, ...) so that both
    see the same load on a shared machine; images/s from the fastest and the median call."""
    images = jax.random.uniform(jax.random.key(1), (batch, size, size, 3), jnp.float32)
    steps, first = {}, {}
    for layout, build in LAYOUTS.items():
        params, loss = build(width, size, jax.random.key(0))
        step = eqx.filter_jit(eqx.filter_value_and_grad(loss))
        start = time.perf_counter()
        jax.block_until_ready(step(params, images))
        first[layout] = time.perf_counter() - start
        steps[layout] = (step, params)
    seconds = {layout: [] for layout in LAYOUTS}
    for _ in range(repeats):
        for layout, (step, params) in steps.items():
            start = time.perf_counter()
            jax.block_until_ready(step(params, images))
            seconds[layout].append(time.perf_counter() - start)
    return [
        {
            "layout": layout,
            "width": width,
            "image_size": size,
            "batch": batch,
            "images_per_s_best": round(batch / min(seconds[layout]), 2),
            "images_per_s_median": round(batch / float(np.median(seconds[layout])), 2),
            "first_call_s": round(first[layout], 2),
            "calls": repeats,
        }
        for layout in LAYOUTS
    ]


def _matmul_gflops() -> float:
    a = jax.random.normal(jax.random.key(0), (1024, 1024), jnp.float32)
    product = jax.jit(lambda a: a @ a)
    jax.block_until_ready(product(a))
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < 2.0:
        jax.block_until_ready(product(a))
        calls += 1
    return 2 * 1024**3 * calls / (time.perf_counter() - start) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two small configurations only (a smoke test)")
    args = parser.parse_args()
    if args.quick:
        configs = [(8, 32, 32)]
    else:
        configs = [(32, 64, 32), (32, 32, 32), (32, 32, 128)]
        configs += [(width, size, batch) for width in (16, 8) for size in (64, 32) for batch in (32, 128)]
    gflops_before = _matmul_gflops()
    rows, ratios = [], []
    for width, size, batch in configs:
        first, last = _time(width, size, batch, repeats=3 if args.quick else 5)
        rows += [first, last]
        ratio = {
            "width": width,
            "image_size": size,
            "batch": batch,
            "channels_first_over_last_best": round(first["images_per_s_best"] / last["images_per_s_best"], 3),
            "channels_first_over_last_median": round(
                first["images_per_s_median"] / last["images_per_s_median"], 3
            ),
        }
        ratios.append(ratio)
        print(first, last, ratio, file=sys.stderr, flush=True)
    gflops_after = _matmul_gflops()
    wins = sum(r["channels_first_over_last_best"] > 1 for r in ratios)
    result = {
        "benchmark": "vision_layout",
        "what": "forward+backward images/s of the A.4 autoencoder (U-Net estimator + U-Net renderer), "
        f"float32, {NUM_KEYPOINTS} keypoints; the two layouts' calls interleaved, best and median of 5",
        "machine": machine(),
        "matmul_gflops_1024_before_after": [round(gflops_before, 1), round(gflops_after, 1)],
        "rows": rows,
        "ratios": ratios,
        "channels_first_faster_in": f"{wins}/{len(ratios)}",
        "choice": "channels_first" if wins * 2 >= len(ratios) else "channels_last",
    }
    if args.quick:
        print(result)
    else:
        write("vision_layout", result)


if __name__ == "__main__":
    main()
