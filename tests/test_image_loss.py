"""The training loss kernels (L1 + w (1 - SSIM), zero-padded SSIM) against the float64 reference:
the loss value and its gradient (float64 central differences of the reference). Tolerances: 1e-5
relative for the value and 1e-3 of the largest gradient component; measured about 1e-7 and 1e-5."""

import numpy as np
import pytest
import reference_refine as ref
import warp as wp

from nanogs_warp.refinement.image_loss import ImageLoss, loss_view, target_views


@pytest.mark.parametrize("shape", [(16, 13), (23, 12)])
def test_loss_and_gradient_match_reference(device, rng, shape):
    h, w = shape
    x = rng.uniform(0.0, 1.0, (h, w, 3))
    y = np.clip(x + rng.normal(0.0, 0.2, (h, w, 3)), 0.0, 1.0)
    x32, y32 = x.astype(np.float32), y.astype(np.float32)
    loss = ImageLoss(h, w, device)
    grad = wp.full((h, w, 3), float("nan"), dtype=wp.float32, device=device)
    loss.loss.fill_(float("nan"))
    loss(wp.array(x32, dtype=wp.float32, device=device), wp.array(y32, dtype=wp.float32, device=device), grad, 0.2, 0.5)
    expected = 0.5 * ref.training_loss(x32, y32, 0.2)
    assert abs(loss.value() - expected) <= 1e-5 * expected

    got = grad.numpy()
    assert np.isfinite(got).all()
    base = x32.astype(np.float64)
    fd = np.empty_like(base)
    step = 1e-6
    for index in np.ndindex(base.shape):
        saved = base[index]
        base[index] = saved + step
        plus = ref.training_loss(base, y32, 0.2)
        base[index] = saved - step
        minus = ref.training_loss(base, y32, 0.2)
        base[index] = saved
        fd[index] = 0.5 * (plus - minus) / (2 * step)
    assert np.abs(got - fd).max() <= 1e-3 * np.abs(fd).max()


def test_identical_images_have_zero_loss(device, rng):
    x = rng.uniform(0.0, 1.0, (20, 24, 3)).astype(np.float32)
    loss = ImageLoss(20, 24, device)
    grad = wp.full((20, 24, 3), float("nan"), dtype=wp.float32, device=device)
    image = wp.array(x, dtype=wp.float32, device=device)
    loss(image, image, grad, 0.2)
    assert abs(loss.value()) <= 1e-6
    assert np.abs(grad.numpy()).max() <= 1e-6


@pytest.mark.parametrize("channels", [6, 9])
@pytest.mark.parametrize("margin", [(0, 0), (3, 6)])
def test_blur_sums_in_its_documented_order(device, rng, channels, margin):
    """The separable blur, both directions, bit for bit against float32 numpy summing in the kernel's
    order: the centre tap, then the other taps that land inside the view, left to right. A thread
    computes RUN pixels side by side: away from the edges in an unrolled loop that shares their loads,
    near them pixel by pixel in a bounded one; both must give these bits (the outputs' bytes, and
    CPU = CUDA, rest on the order). The view (37 x 29: no multiple of RUN) in the corner of a stack
    ``margin`` larger, NaN beyond it: nothing there is read or written."""
    from nanogs_warp.eval.metrics import gaussian_window
    from nanogs_warp.kernels import image_loss as kernels

    h, w = 37, 29
    stack_h, stack_w = h + margin[0], w + margin[1]
    vec = kernels.vec6 if channels == 6 else kernels.vec9
    source = rng.standard_normal((h, w, channels)).astype(np.float32)
    padded = np.full((1, stack_h, stack_w, channels), np.nan, np.float32)
    padded[0, :h, :w] = source
    taps = gaussian_window().astype(np.float32)
    radius = len(taps) // 2
    src = wp.array(padded, dtype=vec, device=device)
    taps_wp = wp.array(taps, dtype=wp.float32, device=device)
    views = wp.array([loss_view(0, w, h, 0.2, 1.0)], dtype=kernels.LossView, device=device)
    for vertical in (0, 1):
        target = wp.full((1, stack_h, stack_w), vec(float("nan")), dtype=vec, device=device)
        threads = kernels.blur_threads(1, stack_h, stack_w, vertical)
        wp.launch(kernels.blur, threads, inputs=[0, src, taps_wp, vertical, views, target], device=device)
        moved = source if vertical == 0 else source.transpose(1, 0, 2)  # blur along axis 1
        expected = taps[radius] * moved
        for j in range(len(taps)):
            if j == radius:
                continue
            shift = j - radius
            term = np.zeros_like(moved)
            lo, hi = max(0, -shift), min(moved.shape[1], moved.shape[1] - shift)
            term[:, lo:hi] = taps[j] * moved[:, lo + shift:hi + shift]
            inside = np.zeros(moved.shape[1], bool)
            inside[lo:hi] = True
            expected = np.where(inside[None, :, None], expected + term, expected)  # float32, in order
        if vertical:
            expected = expected.transpose(1, 0, 2)
        got = target.numpy()[0]
        assert got[:h, :w].tobytes() == np.ascontiguousarray(expected, dtype=np.float32).tobytes()
        assert np.isnan(got[h:]).all() and np.isnan(got[:, w:]).all()


@pytest.mark.parametrize("shape", [(256, 192), (37, 29)])
def test_halved_averages_each_2x2_block(device, rng, shape):
    """``halved``: each pixel of the half-size view the mean of its 2x2 block (an odd last row or
    column dropped), bit for bit against float32 numpy summing the rows first, and within float32
    rounding of the float64 mean. Outputs poisoned with NaN before the launch."""
    from nanogs_warp.kernels import image_loss as kernels

    h, w = shape
    image = rng.random((h, w, 3), dtype=np.float32)
    half = wp.full((h // 2, w // 2, 3), float("nan"), dtype=wp.float32, device=device)
    wp.launch(kernels.halved, (h // 2) * (w // 2), inputs=[0, wp.array(image, dtype=wp.float32, device=device), half],
              device=device)  # fmt: skip
    b = image[: 2 * (h // 2), : 2 * (w // 2)]
    expected = np.float32(0.25) * ((b[0::2, 0::2] + b[0::2, 1::2]) + (b[1::2, 0::2] + b[1::2, 1::2]))
    assert half.numpy().tobytes() == expected.tobytes()
    b64 = b.astype(np.float64)
    mean = (b64[0::2, 0::2] + b64[0::2, 1::2] + b64[1::2, 0::2] + b64[1::2, 1::2]) / 4.0
    assert np.abs(half.numpy() - mean).max() <= 1e-6


def test_views_together_give_each_view_its_own_bits(device, rng):
    """Several views of different sizes in one stack (each in its top-left corner, NaN beyond it),
    their targets picked from another stack: each view's gradient and per-pixel loss are the bits of
    that view's loss computed alone, and nothing beyond a view's size is written."""
    from nanogs_warp.kernels import image_loss as kernels

    sizes = [(23, 12), (16, 13), (11, 17)]  # (height, width), one narrower than the blur window's reach
    height, width = max(h for h, _ in sizes), max(w for _, w in sizes)
    images = np.full((len(sizes), height, width, 3), np.nan, np.float32)
    targets = np.full((4, height, width, 3), np.nan, np.float32)
    chosen = [2, 0, 3]
    for v, (h, w) in enumerate(sizes):
        images[v, :h, :w] = rng.uniform(0.0, 1.0, (h, w, 3))
        targets[chosen[v], :h, :w] = np.clip(images[v, :h, :w] + rng.normal(0.0, 0.2, (h, w, 3)), 0.0, 1.0)
    loss = ImageLoss(height, width, device, views=len(sizes))
    grads = wp.full(images.shape, float("nan"), dtype=wp.float32, device=device)
    specs = [loss_view(k, w, h, 0.2, 0.25) for k, (h, w) in zip(chosen, sizes)]
    target_sizes = [(5, 7)] * len(targets)  # the unused target's: any
    for k, (h, w) in zip(chosen, sizes):
        target_sizes[k] = (w, h)
    stack = target_views(wp.array(targets, dtype=wp.float32, device=device), target_sizes)
    loss.of_views(wp.array(images, dtype=wp.float32, device=device), stack, grads,
                  wp.array(specs, dtype=kernels.LossView, device=device))  # fmt: skip
    got, shares = grads.numpy(), loss.loss.numpy()
    # targets whose blurred terms are not kept: each loss blurs its views' own, the same bits
    unkept = target_views(stack.images, target_sizes, moments=False)
    assert unkept.moments is None
    again = wp.full(images.shape, float("nan"), dtype=wp.float32, device=device)
    loss.loss.fill_(float("nan"))
    loss.of_views(wp.array(images, dtype=wp.float32, device=device), unkept, again,
                  wp.array(specs, dtype=kernels.LossView, device=device))  # fmt: skip
    assert np.array_equal(again.numpy(), got, equal_nan=True) and loss.loss.numpy().tobytes() == shares.tobytes()
    for v, (h, w) in enumerate(sizes):
        alone = ImageLoss(h, w, device)
        grad = wp.full((h, w, 3), float("nan"), dtype=wp.float32, device=device)
        alone(wp.array(images[v, :h, :w].copy(), dtype=wp.float32, device=device),
              wp.array(targets[chosen[v], :h, :w].copy(), dtype=wp.float32, device=device), grad, 0.2, 0.25)  # fmt: skip
        assert got[v, :h, :w].tobytes() == grad.numpy().tobytes()
        assert shares[v, :h, :w].tobytes() == alone.loss.numpy()[0].tobytes()
        assert np.isnan(got[v, h:]).all() and np.isnan(got[v, :, w:]).all()
        assert not shares[v, h:].any() and not shares[v, :, w:].any()


def test_a_targets_blurred_terms_are_its_own_and_made_once(device, rng):
    """``target_views``: each target's G*Y and G*Y^2 per channel, zero-padded at its own size (views of
    different sizes in one stack, NaN beyond each: never read), within float32 rounding of the
    float64 blur; the images are the stack given, not a copy."""
    from nanogs_warp.kernels import image_loss as kernels

    sizes = [(12, 23), (13, 16), (17, 11)]  # (width, height)
    height, width = max(h for _, h in sizes), max(w for w, _ in sizes)
    images = np.full((len(sizes), height, width, 3), np.nan, np.float32)
    for k, (w, h) in enumerate(sizes):
        images[k, :h, :w] = rng.uniform(0.0, 1.0, (h, w, 3))
    given = wp.array(images, dtype=wp.float32, device=device)
    targets = target_views(given, sizes)
    assert targets.images is given
    assert targets.moments.dtype == kernels.vec6 and targets.moments.shape == (len(sizes), height, width)
    got = targets.moments.numpy()
    for k, (w, h) in enumerate(sizes):
        y = images[k, :h, :w].astype(np.float64)
        expected = np.concatenate([ref.blur_same(y), ref.blur_same(y * y)], axis=-1)
        assert np.abs(got[k, :h, :w] - expected).max() <= 1e-6
