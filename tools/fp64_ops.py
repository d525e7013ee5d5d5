"""Counts the float64 operations the cost and merge kernels execute, per edge and per merge, by
running the kernels' own source (kernels/*.py) in Python with a stand-in for Warp whose float64
type counts every operation it does.

    python tools/fp64_ops.py SCENE.ply [--edges 400] [--json]

For a sample of the first pass's candidate edges of SCENE (and its chosen pairs) it reports the
mean number of float64 additions (and subtractions), multiplications, divisions, square roots,
comparisons, min/max and conversions of

- the field cost per edge (the coverage operator's merge scored; --preset default),
- the Runnalls cost per edge (--preset fast) and the idiv cost per edge with one sample (--preset
  paper), and their per-splat terms per splat and pass,
- the coverage and MPMM merges per merged pair,

with a breakdown by device function, and an estimate of what the 6M -> 0.1 run's cost and merge
stages need on GPUs of known float64 rates (--edges-total / --splats-total / --merges-total: the
sums over the run's passes, from ``tools/bench.py --json`` or the pipeline's pass reports).

The stand-in runs the same Python statements Warp compiles, so loop trip counts (the Jacobi
sweeps, early exits) are the real ones for these inputs. Integer and bit operations are not
counted; float32 operations are counted apart (``f32``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import struct
import sys
import types
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
COUNTS: Counter = Counter()
BY_FUNCTION: Counter = Counter()
_STACK: list[str] = ["<kernel>"]


def _count(kind: str, n: int = 1) -> None:
    COUNTS[kind] += n
    if kind != "f32":
        BY_FUNCTION[_STACK[-1]] += n


class F:
    """A float64 that counts its operations."""

    __slots__ = ("v",)

    def __init__(self, v=0.0):
        self.v = float(v.v) if isinstance(v, (F, F32)) else float(v)
        if isinstance(v, F32):
            _count("cvt")

    @staticmethod
    def _v(o):
        return o.v if isinstance(o, (F, F32)) else float(o)

    def _bin(self, o, kind, fn):
        _count(kind)
        return F(fn(np.float64(self.v), np.float64(F._v(o))))

    def __add__(self, o):
        return self._bin(o, "add", lambda a, b: a + b)

    __radd__ = __add__

    def __sub__(self, o):
        return self._bin(o, "add", lambda a, b: a - b)

    def __rsub__(self, o):
        return self._bin(o, "add", lambda a, b: b - a)

    def __mul__(self, o):
        if isinstance(o, (Vec, Mat)):
            return o.__rmul__(self)
        return self._bin(o, "mul", lambda a, b: a * b)

    __rmul__ = __mul__

    def __truediv__(self, o):
        with np.errstate(all="ignore"):
            return self._bin(o, "div", lambda a, b: a / b)

    def __rtruediv__(self, o):
        with np.errstate(all="ignore"):
            return self._bin(o, "div", lambda a, b: b / a)

    def __neg__(self):
        return F(-self.v)  # a sign flip: free (folded into the consumer on a GPU)

    def _cmp(self, o, fn):
        _count("cmp")
        return fn(self.v, F._v(o))

    def __lt__(self, o):
        return self._cmp(o, lambda a, b: a < b)

    def __le__(self, o):
        return self._cmp(o, lambda a, b: a <= b)

    def __gt__(self, o):
        return self._cmp(o, lambda a, b: a > b)

    def __ge__(self, o):
        return self._cmp(o, lambda a, b: a >= b)

    def __eq__(self, o):
        return self._cmp(o, lambda a, b: a == b)

    def __ne__(self, o):
        return self._cmp(o, lambda a, b: a != b)

    __hash__ = None

    def __int__(self):
        _count("cvt")
        return int(self.v) if math.isfinite(self.v) else 0

    def __float__(self):
        return self.v


class F32(F):
    """A float32: counted apart."""

    def __init__(self, v=0.0):
        self.v = float(np.float32(v.v if isinstance(v, F) else v))
        if isinstance(v, F) and not isinstance(v, F32):
            _count("cvt")

    def _bin(self, o, kind, fn):
        if isinstance(o, F) and not isinstance(o, F32):
            return F(self)._bin(o, kind, fn)
        _count("f32")
        return F32(fn(np.float32(self.v), np.float32(F._v(o))))

    def __neg__(self):
        return F32(-self.v)


class Vec(list):
    def __add__(self, o):
        return Vec(a + b for a, b in zip(self, o))

    def __sub__(self, o):
        return Vec(a - b for a, b in zip(self, o))

    def __mul__(self, s):
        return Vec(a * s for a in self)

    def __rmul__(self, s):
        return Vec(s * a for a in self)

    def __neg__(self):
        return Vec(-a for a in self)

    def __iadd__(self, o):  # a list would extend itself
        return self + o

    def __isub__(self, o):
        return self - o


class Mat:
    def __init__(self, rows):
        self.r = [list(row) for row in rows]

    def __getitem__(self, ij):
        return self.r[ij[0]][ij[1]]

    def __setitem__(self, ij, v):
        self.r[ij[0]][ij[1]] = v

    def __add__(self, o):
        return Mat([[a + b for a, b in zip(x, y)] for x, y in zip(self.r, o.r)])

    def __sub__(self, o):
        return Mat([[a - b for a, b in zip(x, y)] for x, y in zip(self.r, o.r)])

    def __rmul__(self, s):
        return Mat([[s * a for a in row] for row in self.r])

    def __mul__(self, o):
        if isinstance(o, Mat):  # Warp's matrix product: fma per term (counted as mul + add)
            out = []
            for i in range(3):
                row = []
                for j in range(3):
                    acc = F(0.0)
                    for k in range(3):
                        acc = acc + self.r[i][k] * o.r[k][j]
                    row.append(acc)
                out.append(row)
            return Mat(out)
        if isinstance(o, Vec):  # column combination, as mat.h does
            acc = Vec(self.r[i][0] * o[0] for i in range(3))
            for k in (1, 2):
                acc = acc + Vec(self.r[i][k] * o[k] for i in range(3))
            return acc
        return self.__rmul__(o)


def _scalar(kind):
    def make(*args):
        if not args:
            return kind(0.0)
        (x,) = args
        if kind is int_ and isinstance(x, F):
            return int(x)
        return kind(x)

    return make


def int_(x=0):
    return int(x.v) if isinstance(x, F) else int(x)


class _Placeholder:
    def __init__(self, *args, **kwargs):
        pass


def _array(*args, **kwargs):
    return _Placeholder


def _cast(x, dtype):
    if dtype is fake.int64:
        return struct.unpack("<q", struct.pack("<d", x.v))[0]
    if dtype is fake.float64:
        return F(struct.unpack("<d", struct.pack("<q", ((int(x) + 2**63) % 2**64) - 2**63))[0])
    raise NotImplementedError(dtype)


def _func(f):
    name = f.__name__

    def wrapper(*args, **kwargs):
        # Warp passes vectors and matrices by value: a function that changes its argument changes a copy
        args = [Mat(a.r) if isinstance(a, Mat) else Vec(a) if isinstance(a, Vec) else a for a in args]
        _STACK.append(name)
        try:
            return f(*args, **kwargs)
        finally:
            _STACK.pop()

    wrapper.__name__ = name
    wrapper.func = f
    return wrapper


def _minmax(pick):
    def fn(a, b):
        if isinstance(a, Vec):
            return Vec(fn(x, y) for x, y in zip(a, b))
        if isinstance(a, F) or isinstance(b, F):
            _count("minmax")
        return pick(a, b)

    return fn


def _sqrt(x):
    _count("sqrt")
    with np.errstate(all="ignore"):
        return F(np.sqrt(np.float64(x.v)))


def _abs(x):
    return F(abs(x.v)) if not isinstance(x, F32) else F32(abs(x.v))


def _dot(a, b):
    acc = a[0] * b[0]
    for k in (1, 2):
        acc = acc + a[k] * b[k]
    return acc


def _outer(a, b):
    return Mat([[a[i] * b[j] for j in range(3)] for i in range(3)])


def _det(m):
    r = m.r
    return (
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
    )


def _isfinite(x):
    if isinstance(x, Vec):
        return all(_isfinite(v) for v in x)
    if isinstance(x, Mat):
        return all(math.isfinite(v.v) for row in x.r for v in row)
    return math.isfinite(x.v) if isinstance(x, F) else math.isfinite(x)


def _mat33d(*args):
    if not args:
        return Mat([[F(0.0)] * 3 for _ in range(3)])
    return Mat([list(args[0:3]), list(args[3:6]), list(args[6:9])])


def _vec(kind, size=3):
    def make(*args):
        if not args:
            return Vec([kind(0.0)] * size)
        if len(args) == 1:
            return Vec([kind(args[0])] * size)
        return Vec(kind(a) if not isinstance(a, F) or kind is F32 else a for a in args)

    return make


fake = types.ModuleType("warp")
fake.float64 = _scalar(F)
fake.float32 = _scalar(F32)
fake.int64 = int_
fake.int32 = int_
fake.uint32 = int_
fake.uint64 = int_
fake.vec3d = _vec(F)
fake.vec4d = _vec(F, 4)
fake.vec4i = _vec(int_, 4)
fake.vec3 = _vec(F32)
fake.vec4 = lambda *a: Vec(F32(x) for x in a)
fake.quat = lambda *a: Vec(F32(x) for x in a)
fake.mat33d = _mat33d
fake.constant = lambda x: x
fake.func = _func
fake.kernel = _func
fake.struct = lambda cls: cls
fake.set_module_options = lambda *a, **k: None
fake.array = _array
fake.array2d = _array
fake.inf = math.inf
fake.nan = math.nan
fake.sqrt = _sqrt
fake.abs = _abs
fake.max = _minmax(lambda a, b: a if a >= b else b)
fake.min = _minmax(lambda a, b: a if a <= b else b)
fake.where = lambda c, a, b: a if c else b
fake.dot = _dot
fake.outer = _outer
fake.transpose = lambda m: Mat([[m.r[j][i] for j in range(3)] for i in range(3)])
fake.diag = lambda v: Mat([[v[i] if i == j else F(0.0) for j in range(3)] for i in range(3)])
fake.identity = lambda n, dtype: Mat([[F(1.0) if i == j else F(0.0) for j in range(3)] for i in range(3)])
fake.determinant = _det
fake.cross = lambda a, b: Vec([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])
fake.cw_mul = lambda a, b: Vec(x * y for x, y in zip(a, b))
fake.isfinite = _isfinite
fake.cast = _cast
fake.clamp = lambda x, lo, hi: fake.min(fake.max(x, lo), hi)
fake.overload = lambda *a, **k: None
fake.tid = lambda: _TID[0]
fake.types = types.SimpleNamespace(vector=lambda **k: _Placeholder)
_TID = [0]


def load_kernels():
    """The kernel files, imported as the package ``opcount`` against the stand-in Warp."""
    package = types.ModuleType("opcount")
    package.__path__ = [str(ROOT / "kernels")]
    saved = sys.modules.get("warp")
    sys.modules["opcount"] = package
    sys.modules["warp"] = fake
    try:
        modules = {}
        for name in ("portable_math", "splat_math", "field", "merge", "cost", "field_cost"):
            spec = importlib.util.spec_from_file_location(f"opcount.{name}", ROOT / "kernels" / f"{name}.py")
            module = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = module
            spec.loader.exec_module(module)
            modules[name] = module
        return modules
    finally:
        if saved is not None:
            sys.modules["warp"] = saved
        else:
            del sys.modules["warp"]


class HostArray:
    """A host array as a kernel sees it: rows as float32 vectors (or F32 scalars)."""

    def __init__(self, data, kind="vec"):
        self.data = data
        self.shape = data.shape
        self.kind = kind

    def __getitem__(self, key):
        value = self.data[key]
        if isinstance(value, np.ndarray):
            return Vec(F32(v) if self.kind == "vec" else F(v) for v in value)
        if self.kind == "mat":
            return value
        return F32(value) if self.data.dtype == np.float32 else (F(value) if self.data.dtype == np.float64 else int(value))

    def __setitem__(self, key, value):
        pass  # outputs are not kept: only the work is counted


class MatArray(HostArray):
    def __init__(self, mats):
        self.mats = mats
        self.shape = (len(mats),)

    def __getitem__(self, key):
        return self.mats[key]


def kernel_view(arrays):
    q = arrays["rotations"][:, [1, 2, 3, 0]]  # Warp's x, y, z, w
    return types.SimpleNamespace(
        means=HostArray(arrays["means"]), rotations=HostArray(np.ascontiguousarray(q)),
        log_scales=HostArray(arrays["log_scales"]), opacities=HostArray(arrays["opacities"]),
        features=HostArray(arrays["features"]), extras=HostArray(arrays["extras"]),
        integer_extras=HostArray(arrays.get("integer_extras", np.zeros((len(q), 0), np.int64))),
    )  # fmt: skip


def measure(call, count: int) -> tuple[dict, dict]:
    """Mean counts per call over ``count`` calls of ``call(index)``."""
    COUNTS.clear()
    BY_FUNCTION.clear()
    for t in range(count):
        _TID[0] = t
        call(t)
    return {k: v / count for k, v in sorted(COUNTS.items())}, {k: v / count for k, v in BY_FUNCTION.most_common(8)}


# GPU cycles per operation on the float64 pipe (CUDA's IEEE double division and square root are
# reciprocal/rsqrt seeds refined by about 8-10 FP64 FMAs, with a fix-up; counted as 10 each).
WEIGHTS = {"add": 1, "mul": 1, "cmp": 1, "minmax": 1, "cvt": 1, "div": 10, "sqrt": 10}
# Published float64 rates (an FMA counts as two FLOPs; these kernels do not fuse, so the rate of
# separate adds and multiplies is half): RTX 4090 1.29 TFLOPS; H100 SXM 34 TFLOPS on its vector
# units (67 TFLOPS is its FP64 tensor-core rate, which these kernels cannot use).
GPUS = {"RTX 4090": 1.29e12, "H100 SXM (vector)": 34e12, "H100 SXM (tensor rate)": 67e12}


def weighted(counts: dict) -> float:
    return sum(WEIGHTS.get(k, 0) * v for k, v in counts.items())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a 3DGS .ply file")
    parser.add_argument("--edges", type=int, default=400, help="edges (and pairs) sampled")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--edges-total", type=float, default=None, help="candidate edges summed over a run's passes")
    parser.add_argument("--splats-total", type=float, default=None, help="splats summed over a run's passes")
    parser.add_argument("--merges-total", type=float, default=None, help="merges over a run")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)

    import warp as wp

    from nanogs_warp.device import init_warp
    from nanogs_warp.pairing import select_pairs
    from nanogs_warp.io.ply import load_ply
    from nanogs_warp.cost import FieldCost, reference_energy
    from nanogs_warp.operators import COVERAGE_GROWTH
    from nanogs_warp.timing import no_clock
    from nanogs_warp.topology import KnnTopology

    init_warp()
    splats = load_ply(args.scene).to("cpu")
    edges = KnnTopology(16)(splats, no_clock)
    costs = FieldCost()(splats, edges, 0)
    pairs = select_pairs(edges, costs, splats.count, cap=splats.count // 3)
    rng = np.random.default_rng(args.seed)
    pick = rng.choice(edges.count, size=min(args.edges, edges.count), replace=False)
    ei, ej = edges.i.numpy()[pick], edges.j.numpy()[pick]
    take = rng.choice(pairs.count, size=min(args.edges, pairs.count), replace=False)
    pi_, pj_ = pairs.i.numpy()[take], pairs.j.numpy()[take]
    arrays = splats.to_numpy()
    k = load_kernels()
    src = kernel_view(arrays)
    n = splats.count
    rows = np.unique(np.concatenate([ei, ej, pi_, pj_]))

    # per-splat terms, once a pass: the field cost's covariances, Runnalls' covariances, log dets, weights
    covs = {}

    norms = {}
    alphas = {}
    log_weights = {}

    def splat_terms(t):
        i = int(rows[t])
        covs[i] = k["splat_math"].covariance(src.rotations[i], src.log_scales[i])
        norms[i] = k["field_cost"].colour_dot(src.features, i, i)
        alphas[i], log_weights[i] = k["merge"].coverage_terms(src.opacities[i], src.log_scales[i])

    per_splat_field, _ = measure(splat_terms, len(rows))
    mats = MatArray({int(r): covs[int(r)] for r in rows})
    colour_norms = MatArray({int(r): norms[int(r)] for r in rows})
    alpha_of = MatArray({int(r): alphas[int(r)] for r in rows})
    log_weight_of = MatArray({int(r): log_weights[int(r)] for r in rows})
    one = HostArray(np.zeros(1, np.float32))
    rot, ls, op = src.rotations, src.log_scales, src.opacities
    per_splat_runnalls, _ = measure(
        lambda t: k["cost"].runnalls_splat_terms(rot, ls, op, one, one, one) if not _TID.__setitem__(0, int(rows[t])) else None,
        len(rows),
    )
    edge_i, edge_j = HostArray(ei.astype(np.int32)), HostArray(ej.astype(np.int32))
    out = HostArray(np.zeros(len(ei), np.float32))
    energy = HostArray(reference_energy(splats).numpy())  # E_ref of the contrast term: once a pass
    contrast = FieldCost.lambda_contrast
    field, field_by = measure(
        lambda t: k["field_cost"].field_costs(edge_i, edge_j, src, mats, colour_norms, alpha_of, log_weight_of, 1, FieldCost.growth, 1.0, 1.0, contrast, energy, out), len(ei)
    )
    field_mpmm, _ = measure(
        lambda t: k["field_cost"].field_costs(edge_i, edge_j, src, mats, colour_norms, alpha_of, log_weight_of, 0, FieldCost.growth, 1.0, 1.0, contrast, energy, out), len(ei)
    )
    weights = MatArray({int(r): F(1.0) for r in rows})
    log_dets = MatArray({int(r): F(-10.0) for r in rows})
    runnalls, runnalls_by = measure(
        lambda t: k["cost"].runnalls_costs(edge_i, edge_j, src.means, mats, weights, log_dets, src.features, 1.0, 1.0, 0.25, out),
        len(ei),
    )
    samples = HostArray(np.array([[0.3, -1.1, 0.7]], np.float32))
    idiv, idiv_by = measure(
        lambda t: k["cost"].idivergence_costs(edge_i, edge_j, src.means, rot, ls, op, src.features, samples, 1.0, 1.0, out),
        len(ei),
    )
    pair_i, pair_j = HostArray(pi_.astype(np.int32)), HostArray(pj_.astype(np.int32))
    destination = HostArray(np.arange(n, dtype=np.int32))
    sink = types.SimpleNamespace(**{key: HostArray(np.zeros((1, 1), np.float32)) for key in vars(src)})
    coverage, coverage_by = measure(lambda t: k["merge"].coverage_moment_matching(pair_i, pair_j, destination, src, sink, COVERAGE_GROWTH), len(pi_))
    mpmm, _ = measure(lambda t: k["merge"].mass_preserving_moment_matching(pair_i, pair_j, destination, src, sink), len(pi_))

    report = {
        "scene": args.scene.name, "edges_sampled": len(ei), "pairs_sampled": len(pi_),
        "per_edge": {"field (coverage)": field, "field (mpmm)": field_mpmm, "runnalls": runnalls, "idiv, 1 sample": idiv},
        "per_splat_per_pass": {"field: covariance, colour norm": per_splat_field, "runnalls: terms": per_splat_runnalls},
        "per_merge": {"coverage": coverage, "mpmm": mpmm},
        "by_function": {"field (coverage)": field_by, "runnalls": runnalls_by, "idiv": idiv_by, "coverage merge": coverage_by},
        "weights": WEIGHTS,
    }  # fmt: skip
    if args.edges_total and args.splats_total and args.merges_total:
        work = {
            "default (field cost, coverage merge)": args.edges_total * weighted(field) + args.splats_total * weighted(per_splat_field) + args.merges_total * weighted(coverage),
            "fast (runnalls, coverage merge)": args.edges_total * weighted(runnalls) + args.splats_total * weighted(per_splat_runnalls) + args.merges_total * weighted(coverage),
        }  # fmt: skip
        report["run_fp64_ops"] = work
        report["run_seconds_at_fp64_rate"] = {
            preset: {gpu: ops / (rate / 2) for gpu, rate in GPUS.items()} for preset, ops in work.items()
        }
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"{report['scene']}: {len(ei)} edges and {len(pi_)} merges sampled from the first pass")
    for group in ("per_edge", "per_splat_per_pass", "per_merge"):
        for name, counts in report[group].items():
            body = " ".join(f"{key}={value:.0f}" for key, value in counts.items())
            print(f"  {group:>18} {name:>22}: weighted {weighted(counts):7.0f}  ({body})")
    for name, parts in report["by_function"].items():
        print(f"  {name:>22} by function: " + ", ".join(f"{f} {v:.0f}" for f, v in parts.items()))
    if "run_fp64_ops" in report:
        for preset, ops in report["run_fp64_ops"].items():
            times = ", ".join(f"{gpu} {s * 1e3:.0f} ms" for gpu, s in report["run_seconds_at_fp64_rate"][preset].items())
            print(f"  run, {preset}: {ops:.3g} weighted FP64 ops -> {times}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
