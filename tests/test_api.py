"""The Python API as a library user meets it: several budgets in one call, configurations checked
where they are built, the package's own error for a missing device."""

import os
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

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


def test_the_budgets_order_changes_no_output(splats):
    # an output depends on the set of budgets asked for together (README, "Budgets"), not their order
    a = simplify(splats, ratios=[0.1, 0.01], device="cpu")
    b = simplify(splats, ratios=[0.01, 0.1], device="cpu")
    assert same(a[0], b[1]) and same(a[1], b[0])


def test_several_counts_and_repeats(splats):
    results = simplify(splats, counts=(100, 10, 100))
    assert [r.count for r in results] == [100, 10, 100]
    assert [r.count for r in simplify(splats, count=[50])] == [50]
    assert simplify(splats, count=np.int64(20)).count == 20
    assert simplify(splats, ratio=np.float32(0.07)).count == 49  # ceil(0.07 * 700) exactly
    assert simplify(splats, ratio=np.float64(0.07)).count == 49  # numpy's float64 is a float: its shortest repr
    assert [r.count for r in simplify(splats, ratio=list(np.linspace(0.1, 0.3, 3)))] == [70, 140, 210]


@pytest.mark.parametrize(
    "kwargs",
    [{}, {"ratio": 0.1, "count": 5}, {"ratio": 0.1, "ratios": [0.2]}, {"count": 5, "counts": [3]}, {"ratios": []},
     {"count": 2.5}, {"ratio": [0.1, 2.0]}, {"count": [701]}, {"count": float("nan")}, {"count": float("inf")},
     {"count": "5"}, {"ratio": np.float64("nan")}],
)  # fmt: skip
def test_bad_budgets(splats, kwargs):
    with pytest.raises(InputError):
        simplify(splats, **kwargs)


@pytest.mark.parametrize(
    "kwargs",
    [{"operator": "nope"}, {"cost": "nope"}, {"k": 0}, {"k": 1000}, {"prune_opacity": 1.5}, {"samples": 0},
     {"lambda_geo": -1.0}, {"lambda_app": float("nan")}, {"k": "24"}, {"k": 2.0}, {"fit_size": 1}, {"cost": None},
     {"seed": -1}, {"seed": 2**31}, {"pass_fraction": "0.3"}],
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
    with pytest.raises(InputError, match=rf"^--device {missing}: "):  # Warp's RuntimeError before
        splats.to(missing)
    with pytest.raises(InputError, match=rf"^--device {missing}: "):
        SplatSet.from_numpy(**random_splat_arrays(5, sh_degree=0, seed=1), device=missing)
    for odd in (0, 1.5, b"cpu"):  # Warp's ValueError "Invalid device identifier" before
        with pytest.raises(InputError, match="device must be auto, cpu, cuda, cuda:N or a Warp device"):
            simplify(splats, ratio=0.1, device=odd)


def test_a_missing_device_is_the_packages_error_when_loading_and_refining(splats, tmp_path):
    """load_ply, load_splats and refine gave Warp's RuntimeError or ValueError for a device name
    (and a GPU this machine lacks printed native CUDA lines), where simplify gave the InputError."""
    from nanogs_warp import load_ply, load_splats, refine, save_ply

    save_ply(splats, tmp_path / "s.ply")
    missing = f"cuda:{wp.get_cuda_device_count()}"
    for load in (load_ply, load_splats):
        for device, message in ((missing, rf"^--device {missing}: "), ("gpu", "expected auto, cpu, cuda or cuda:N")):
            with pytest.raises(InputError, match=message):
                load(tmp_path / "s.ply", device=device)
    with pytest.raises(InputError, match="expected auto, cpu, cuda or cuda:N"):
        refine(splats, splats, device="gpu")
    with pytest.raises(InputError, match=rf"^--device {missing}: "):
        refine(splats, splats, device=missing)


def test_calls_on_one_device_take_turns(splats):
    """Several threads' calls on one device ran at once, and on a GPU met illegal memory accesses:
    each call now holds its device's lock while it works there, and a progressive run holds it only
    while it makes each output."""
    import threading

    from nanogs_warp.device import device_lock

    fast = SimplifyConfig.preset("fast")
    alone = simplify(splats, ratio=0.5, device="cpu", config=fast).to_numpy()
    lock, results = device_lock(wp.get_device("cpu")), []
    with lock:  # held here: another thread's call on the CPU waits for it
        worker = threading.Thread(target=lambda: results.append(simplify(splats, ratio=0.5, device="cpu", config=fast)))
        worker.start()
        worker.join(timeout=2.0)
        assert worker.is_alive() and not results
    worker.join(timeout=120)
    assert len(results) == 1 and all(np.array_equal(results[0].to_numpy()[k], alone[k]) for k in alone)
    steps = simplify_progressively(splats, [splats.count // 2, splats.count // 4], fast)
    next(steps)
    other = threading.Thread(target=lambda: results.append(simplify(splats, ratio=0.5, device="cpu", config=fast)))
    other.start()  # between two outputs the lock is free
    other.join(timeout=120)
    assert len(results) == 2 and next(steps)[0] == splats.count // 4


def test_threads_that_name_a_device_leave_stderr_and_warps_settings_alone():
    """Every call that named a device started Warp again with stderr (file descriptor 2) captured
    in a temporary file: from several threads at once, one restored another's, and the process's
    stderr went to a deleted file for good. Each call also set Warp's log level again. Warp now
    starts once; a fresh process, four threads of many calls."""
    code = (
        "import os, sys\n"
        "from concurrent.futures import ThreadPoolExecutor\n"
        "import warp as wp\n"
        "import nanogs_warp as ng\n"
        "from scene_factory import random_splat_arrays\n"
        "small = ng.SplatSet.from_numpy(**random_splat_arrays(64, seed=2))\n"
        "stderr = os.readlink('/proc/self/fd/2') if os.path.exists('/proc/self/fd/2') else None\n"
        "cfg = ng.SimplifyConfig.preset('fast')\n"
        "with ThreadPoolExecutor(4) as pool:\n"
        "    list(pool.map(lambda _: [ng.simplify(small, count=32, device='cpu', config=cfg) for _ in range(150)], range(4)))\n"
        "wp.config.log_level = wp.LOG_INFO\n"
        "ng.simplify(small, count=32, device='cpu', config=cfg)\n"
        "print('still here', stderr is None or os.readlink('/proc/self/fd/2') == stderr, wp.config.log_level == wp.LOG_INFO, file=sys.stderr)\n"
    )  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines()[-1:] == ["still here True True"], result.stderr


def test_arguments_of_the_wrong_kind_are_named(splats, tmp_path):
    from nanogs_warp import refine

    with pytest.raises(TypeError, match="expected a SplatSet .* got str"):
        simplify(str(tmp_path / "scene.ply"), ratio=0.5)
    with pytest.raises(TypeError, match="config must be a SimplifyConfig"):
        simplify(splats, ratio=0.5, config={"k": 3})
    with pytest.raises(TypeError, match="reference must be a SplatSet"):
        refine(splats, None, steps=1)
    with pytest.raises(InputError, match="RefineConfig.steps must be a whole number, got 2.5"):
        refine(splats, splats, steps=2.5)
    with pytest.raises(InputError, match="--seed must be between 0 and"):
        refine(splats, splats, steps=1, seed=-1)


def test_arrays_of_the_wrong_shape_are_refused_by_name(splats):
    """A kernel handed an array shorter than the means would read and write memory it does not
    own: every array is checked where a splat set is built."""
    arrays = random_splat_arrays(50, sh_degree=1, seed=2)
    cases = [
        ({"rotations": arrays["rotations"][:1]}, "rotations must be an array of shape (N, 4) with N = 50"),
        ({"log_scales": arrays["log_scales"][:, :2]}, "log_scales must be an array of shape (N, 3)"),
        ({"opacities": arrays["opacities"][:49]}, "opacities must be an array of shape (N,) with N = 50"),
        ({"features": arrays["features"][:, :5]}, "5 SH coefficients is not 3 * (d + 1)^2"),
        ({"features": arrays["features"][:, 0]}, "features must be an array of shape (N, columns)"),
        ({"means": arrays["means"].astype(str)}, "means must hold real numbers"),
        ({"extras": np.zeros((49, 2))}, "extras must be an array of shape (N, columns) with N = 50"),
    ]
    for change, message in cases:
        with pytest.raises(ValueError) as caught:
            SplatSet.from_numpy(**{**arrays, **change}, device="cpu")
        assert message in str(caught.value), (change.keys(), str(caught.value))
    assert SplatSet.from_numpy(**{**arrays, "opacities": arrays["opacities"].reshape(50, 1)}, device="cpu").count == 50

    good = SplatSet.from_numpy(**arrays, device="cpu")
    for field, array, message in [
        ("log_scales", wp.zeros(5, dtype=wp.vec3), "SplatSet.log_scales has 5 rows, not one per splat (50"),
        ("rotations", wp.zeros(50, dtype=wp.vec4), "SplatSet.rotations must be a 1-D Warp array of quat"),
        ("opacities", wp.zeros(50, dtype=wp.float64), "SplatSet.opacities must be a 1-D Warp array of float32"),
        ("features", wp.zeros((50, 7), dtype=wp.float32), "7 SH coefficients"),
        ("extras", np.zeros((50, 0), np.float32), "SplatSet.extras must be a Warp array, got ndarray"),
    ]:
        with pytest.raises((ValueError, TypeError)) as caught:
            replace(good, **{field: array})
        assert message in str(caught.value), (field, str(caught.value))


def test_values_a_file_may_not_hold_are_refused_unless_asked(splats):
    arrays = random_splat_arrays(50, sh_degree=1, seed=2)
    nan_features = arrays["features"].copy()
    nan_features[3, 4] = np.nan
    zero_quaternion = arrays["rotations"].copy()
    zero_quaternion[[5, 6]] = 0
    huge = arrays["log_scales"].copy()
    huge[7, 0] = 200
    beyond_float32 = arrays["means"].astype(np.float64)
    beyond_float32[9, 1] = 1e300
    below_float32 = arrays["rotations"].astype(np.float64)
    below_float32[4] = [1e-50, 0, 0, 0]  # 0 in float32: the output's file would be refused
    nan_extras = np.zeros((50, 2), np.float32)
    nan_extras[[1, 2], 1] = [np.nan, np.inf]
    for change, message in [
        ({"features": nan_features}, "1 of 50 splats are invalid: 1 with NaN/Inf features"),
        ({"rotations": zero_quaternion}, "2 of 50 splats are invalid: 2 with zero-norm quaternions"),
        ({"log_scales": huge}, "1 of 50 splats are invalid: 1 with log-scales outside"),
        ({"means": beyond_float32}, "1 of 50 splats are invalid: 1 with NaN/Inf means"),
        ({"rotations": below_float32}, "1 of 50 splats are invalid: 1 with zero-norm quaternions"),
        ({"extras": nan_extras}, "2 of 50 splats are invalid: 2 with NaN/Inf extras"),
    ]:
        with pytest.raises(InputError, match=re.escape(message)):
            SplatSet.from_numpy(**{**arrays, **change}, device="cpu")
        assert SplatSet.from_numpy(**{**arrays, **change}, device="cpu", validate=False).count == 50
    logits = arrays["opacities"].copy()
    logits[:2] = [np.inf, -np.inf]  # alpha 1 and 0: valid, as in a file
    assert SplatSet.from_numpy(**{**arrays, "opacities": logits}, device="cpu").count == 50


def test_integer_extras_must_be_whole_numbers_int64_holds():
    """NaN became INT64_MIN and 2^64 - 1 became -1, silently."""
    arrays = random_splat_arrays(20, sh_degree=0, seed=2)
    for values, message in [(np.full((20, 1), np.nan), "row 0, column 0 holds nan"), (np.full((20, 1), 0.5), "holds 0.5"),
                            (np.full((20, 1), 1e30), "whole numbers within int64"),
                            (np.full((20, 1), 2**64 - 1, np.uint64), "above int64's largest")]:  # fmt: skip
        with pytest.raises(ValueError, match=re.escape(message)):
            SplatSet.from_numpy(**arrays, integer_extras=values, device="cpu")
    kept = SplatSet.from_numpy(**arrays, integer_extras=np.full((20, 1), 7.0), device="cpu")
    assert kept.to_numpy()["integer_extras"].ravel().tolist() == [7] * 20


def test_budgets_and_settings_as_numpy_values(splats):
    """A string is one budget, bytes are refused, 0-d arrays and NumPy's integers are numbers, and the
    result of a budget that keeps every splat is a copy, never the caller's own splat set."""
    assert [r.count for r in simplify(splats, ratios="0.1")] == [70]
    assert simplify(splats, ratio=np.array(0.1)).count == simplify(splats, count=np.array(70)).count == 70
    for kwargs in ({"ratio": b"0.1"}, {"ratio": object()}, {"count": np.bool_(True)}):
        with pytest.raises(InputError):
            simplify(splats, **kwargs)
    whole = simplify(splats, ratio=1)
    assert whole is not splats and same(whole, splats)
    config = SimplifyConfig(k=np.int64(8), cost="idiv", samples=np.int32(2), prune_opacity=np.float32(0.25))
    assert config == SimplifyConfig(k=8, cost="idiv", samples=2, prune_opacity=float(np.float32(0.25)))
    assert type(config.k) is int and simplify(splats, count=100, config=config).count == 100
    with pytest.raises(InputError, match="median-cost-factor"):
        SimplifyConfig(median_cost_factor=10**400)



def test_budgets_in_a_set_are_refused_and_a_repeated_budget_gets_its_own_copy(splats):
    """A set's order changed with PYTHONHASHSEED, and so did the list returned for it; a budget given
    twice returned the same splat set twice, so changing one result changed the other."""
    for kwargs in ({"ratio": {0.1, 0.2}}, {"ratios": frozenset({"0.1"})}, {"count": {70: 1}}, {"counts": {70, 7}}):
        with pytest.raises(InputError, match="must be a list or tuple of budgets"):
            simplify(splats, **kwargs)
    first, again, other = simplify(splats, ratio=[0.1, 0.1, 0.01])
    assert first is not again and same(first, again) and first.means.ptr != again.means.ptr
    assert [first.count, other.count] == [70, 7]

def test_an_empty_splat_set_converts_to_host_arrays():
    empty = SplatSet.from_numpy(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), device="cpu")
    shapes = {k: v.shape for k, v in empty.to_numpy().items()}
    assert shapes == {"means": (0, 3), "rotations": (0, 4), "log_scales": (0, 3), "opacities": (0,), "features": (0, 3),
                      "extras": (0, 0), "integer_extras": (0, 0)}  # fmt: skip


@pytest.mark.parametrize("name", ["e.ply", "e.spz", "e.sog", "e.splat", "e.compressed.ply", "lod-meta.json"])
def test_an_empty_splat_set_is_not_written(tmp_path, name):
    """No reader takes a scene without splats, so no writer makes one: one clear error, no file."""
    from nanogs_warp import save_ply
    from nanogs_warp.io import save_splats

    empty = SplatSet.from_numpy(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), device="cpu")
    for save in (save_splats, save_ply) if name.endswith(".ply") else (save_splats,):
        with pytest.raises(InputError, match="an empty splat set cannot be written"):
            save(empty, tmp_path / name)
    assert list(tmp_path.iterdir()) == []
