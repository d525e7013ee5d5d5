"""The CPU and a CUDA GPU give the same output, byte for byte, for every preset (README, Devices).

The scenes are random and off any lattice: clustered float positions, scales, rotations, opacities
and SH coefficients, so distances, costs and merges all round, and one differently rounded bit
(a fused multiply-add, a library exp) would reorder neighbours or merges and change the output.
Skipped without a GPU; ``pytest -k cuda`` selects these on a GPU machine."""

import numpy as np
import pytest
import warp as wp

from nanogs_warp.pipeline import SimplifyConfig, simplify
from nanogs_warp.splats import SplatSet

HAS_CUDA = wp.get_cuda_device_count() > 0 and wp.is_cpu_available()  # both back-ends: a Warp build without its CPU compiler cannot compare

CONFIGS = {
    "default": SimplifyConfig(),
    "fast": SimplifyConfig.preset("fast"),
    "paper": SimplifyConfig.preset("paper"),
    "paper-4-samples": SimplifyConfig.preset("paper", samples=4, seed=3),
    "field-mpmm": SimplifyConfig(operator="mpmm"),
    "runnalls-area": SimplifyConfig(cost="runnalls", operator="area"),
    "mse-coverage": SimplifyConfig(cost="mse", pass_fraction=0.25),
}


def random_scene(n: int, sh_degree: int, seed: int) -> dict[str, np.ndarray]:
    """Clusters of splats at random float positions (no lattice), anisotropic scales, random
    rotations, opacities and SH; a few exact duplicates and needle-thin splats among them."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(max(1, n // 150), 3)) * rng.uniform(0.5, 7.3)
    spread = rng.uniform(0.003, 0.4, size=(n, 1))
    means = centres[rng.integers(len(centres), size=n)] + rng.normal(size=(n, 3)) * spread + rng.uniform(-30.0, 30.0)
    log_scales = np.log(spread) + rng.normal(scale=0.8, size=(n, 3)) - 1.3
    thin = rng.random(n) < 0.02
    log_scales[thin, 2] -= rng.uniform(4, 12, thin.sum())
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    arrays = {
        "means": means.astype(np.float32),
        "rotations": q.astype(np.float32),
        "log_scales": log_scales.astype(np.float32),
        "opacities": rng.normal(scale=2.5, size=n).astype(np.float32),
        "features": rng.normal(scale=0.6, size=(n, 3 * (sh_degree + 1) ** 2)).astype(np.float32),
        "extras": rng.normal(size=(n, 2)).astype(np.float32),
    }
    copies = rng.integers(n, size=n // 50)
    for key in arrays:
        arrays[key][copies[: len(copies) // 2]] = arrays[key][copies[len(copies) // 2 :]]
    return arrays


def outputs(arrays, device, config, ratios):
    splats = SplatSet.from_numpy(**arrays, device=device)
    return [result.to_numpy() for result in simplify(splats, ratio=ratios, config=config)]


@pytest.mark.skipif(not HAS_CUDA, reason="compares the CPU with a CUDA GPU (needs Warp's CPU compiler too)")
@pytest.mark.parametrize("name", sorted(CONFIGS))
@pytest.mark.parametrize("n, sh_degree, seed", [(6000, 1, 11), (2500, 3, 12)])
def test_simplify_same_on_cpu_and_cuda(name, n, sh_degree, seed):
    arrays = random_scene(n, sh_degree, seed)
    ratios = [0.3, 0.05, 0.01]
    cpu = outputs(arrays, "cpu", CONFIGS[name], ratios)
    gpu = outputs(arrays, "cuda:0", CONFIGS[name], ratios)
    for ratio, a, b in zip(ratios, cpu, gpu):
        for key in a:
            assert a[key].tobytes() == b[key].tobytes(), f"{name}, ratio {ratio}: {key} differs"


@pytest.mark.skipif(not wp.is_cpu_available(), reason="needs Warp's CPU compiler")
def test_random_scene_is_off_lattice_and_simplifies_on_cpu():
    """The scene the CUDA comparison uses is what it claims (not on a grid: distances round) and
    simplifies to the exact budgets on the CPU (so the comparison has outputs to compare)."""
    arrays = random_scene(2000, 1, 5)
    a, b = arrays["means"][:1000], arrays["means"][1000:]
    d32 = ((a - b) ** 2).sum(axis=1, dtype=np.float32)
    d64 = ((a.astype(np.float64) - b.astype(np.float64)) ** 2).sum(axis=1)
    assert np.mean(d32.astype(np.float64) != d64) > 0.9  # float32 squared distances round
    results = outputs(arrays, "cpu", CONFIGS["default"], [0.3, 0.05])
    assert [len(r["means"]) for r in results] == [600, 100]
    assert all(np.all(np.isfinite(r["means"])) for r in results)


@pytest.mark.skipif(not HAS_CUDA, reason="compares the CPU with a CUDA GPU (needs Warp's CPU compiler too)")
@pytest.mark.parametrize("chunk", [5, 2048])
def test_renders_same_on_cpu_and_cuda(chunk):
    """The renderer (the size fit's and refinement's images, ``eval``'s): the same bits on both
    devices, with tiles long enough to be composited in chunks (``chunk`` 5) and in one walk."""
    from nanogs_warp.eval.render import _Rasteriser
    from nanogs_warp.refinement.cameras import training_cameras

    arrays = random_scene(3000, 3, 21)
    cameras = training_cameras(arrays["means"], 6, 48, seed=2)
    images = []
    for device in ("cpu", "cuda:0"):
        splats = SplatSet.from_numpy(**arrays, device=device)
        rasteriser = _Rasteriser(splats, chunk=chunk)
        image = wp.full((len(cameras), 48, 48, 3), float("nan"), dtype=wp.float32, device=device)
        for view, camera in enumerate(cameras):
            if (camera.width, camera.height) == (48, 48):
                rasteriser.render_into(camera, wp.vec3(0.1, 0.2, 0.3), image, view)
        images.append(image.numpy())
    assert images[0].tobytes() == images[1].tobytes()
    assert np.isfinite(images[0]).sum() >= 48 * 48 * 3  # at least one square view was drawn


@pytest.mark.skipif(not HAS_CUDA, reason="compares the CPU with a CUDA GPU (needs Warp's CPU compiler too)")
def test_size_fit_and_refinement_same_on_cpu_and_cuda():
    """The default's size fit (renders of the input, a factor chosen by their PSNR) and refinement
    (renders, the hand-written backward, Adam): the same bytes on both devices."""
    from nanogs_warp import refine
    from nanogs_warp.refinement.simplify import simplify as fitted_simplify

    arrays = random_scene(4000, 1, 23)
    results = []
    for device in ("cpu", "cuda:0"):
        splats = SplatSet.from_numpy(**arrays, device=device)
        small = fitted_simplify(splats, ratio=[0.01, 0.005])
        results.append([s.to_numpy() for s in small] + [refine(small[0], splats, steps=12, size=48).to_numpy()])
    for a, b in zip(*results):
        for key in a:
            assert a[key].tobytes() == b[key].tobytes(), f"{key} differs"
