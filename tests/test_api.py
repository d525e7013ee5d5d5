"""The Python API as a library user meets it: several budgets in one call, configurations checked
where they are built, the package's own error for a missing device."""

import numpy as np
import pytest
import warp as wp
from scene_factory import random_splat_arrays

from nanogs_warp import InputError, SimplifyConfig, SplatSet, simplify, simplify_progressively


@pytest.fixture
def splats():
    return SplatSet.from_numpy(**random_splat_arrays(700, sh_degree=1, seed=5), device="cpu")


def same(a: SplatSet, b: SplatSet) -> bool:
    x, y = a.to_numpy(), b.to_numpy()
    return all(np.array_equal(x[key], y[key]) for key in x)


@pytest.mark.parametrize("keyword", ["ratio", "ratios"])
def test_several_ratios_in_the_order_given(splats, keyword):
    results = simplify(splats, **{keyword: [0.01, 0.1, 0.05]}, device="cpu")
    assert isinstance(results, list) and [r.count for r in results] == [7, 70, 35]
    # one progressive run: each equals the progressive generator's output for its target
    progressive = dict(simplify_progressively(splats, [70, 35, 7]))
    for result in results:
        assert same(result, progressive[result.count])


def test_several_counts_and_repeats(splats):
    results = simplify(splats, counts=(100, 10, 100))
    assert [r.count for r in results] == [100, 10, 100]
    assert [r.count for r in simplify(splats, count=[50])] == [50]
    assert simplify(splats, count=np.int64(20)).count == 20
    assert simplify(splats, ratio=np.float32(0.07)).count == 49  # ceil(0.07 * 700) exactly


@pytest.mark.parametrize(
    "kwargs",
    [{}, {"ratio": 0.1, "count": 5}, {"ratio": 0.1, "ratios": [0.2]}, {"count": 5, "counts": [3]}, {"ratios": []},
     {"count": 2.5}, {"ratio": [0.1, 2.0]}, {"count": [701]}],
)  # fmt: skip
def test_bad_budgets(splats, kwargs):
    with pytest.raises(InputError):
        simplify(splats, **kwargs)


@pytest.mark.parametrize(
    "kwargs",
    [{"operator": "nope"}, {"cost": "nope"}, {"k": 0}, {"k": 1000}, {"prune_opacity": 1.5}, {"samples": 0},
     {"lambda_geo": -1.0}, {"lambda_app": float("nan")}],
)  # fmt: skip
def test_bad_configuration_fails_when_built(kwargs):
    with pytest.raises(InputError):
        SimplifyConfig(**kwargs)
    with pytest.raises(InputError):
        SimplifyConfig.paper(**kwargs)


def test_missing_gpu_is_the_packages_error(splats):
    """A device this machine lacks: InputError with the command line's message, not Warp's."""
    gpus = wp.get_cuda_device_count()
    missing = f"cuda:{gpus}"
    with pytest.raises(InputError, match=rf"^--device {missing}: "):
        simplify(splats, ratio=0.1, device=missing)
    with pytest.raises(InputError, match="expected auto, cpu, cuda or cuda:N"):
        simplify(splats, ratio=0.1, device="tpu")
    assert simplify(splats, ratio=0.1, device="cpu").device == wp.get_device("cpu")
