"""The NanoGS simplification loop (Algorithm 1): prune, then pass after pass
kNN graph -> edge costs -> disjoint greedy pairs -> merge, until the target count."""

from __future__ import annotations

import dataclasses
import math
import numbers
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence, Set
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from .compact import merged_rows_after, remove_rows
from .config import K_LARGE_SCENE, K_SMALL_SCENE, PRESETS, SMALL_SCENE_SPLATS, SimplifyConfig, exact_ratio, finite, target_count  # noqa: F401
from .cost import COSTS, FieldCost
from .errors import InputError, NanogsWarning
from .operators import OPERATORS
from .pairing import cheap_pairs, select_pairs
from .prune import prune_low_opacity
from .splats import SplatSet
from .timing import StageClock, no_clock
from .topology import KnnTopology

if TYPE_CHECKING:
    import warp as wp

    from .io.ply_layout import PlyLayout


# The kNN table (N x k neighbour slots) and the edge offsets are indexed with int32, as Warp's
# array lengths are: N k must stay below this. A module constant so that tests can lower it.
INDEX_LIMIT = 2**31


def pass_limit(start_count: int, target: int, pass_fraction: float = 0.5) -> int:
    """Most passes a run from ``start_count`` splats down to ``target`` may take before it is
    stopped as stuck. A pass pairs off a large share of the splats (greedy matching on a kNN graph
    whose every vertex has an edge: about a third or more of them in practice, at least one pair by
    construction), capped at ``pass_fraction`` of them; the bound allows an eighth of that pace,
    8 x (0.5 / pass_fraction) passes per halving, plus 32."""
    halvings = max(0, math.ceil(math.log2(max(start_count, 1) / max(target, 1))))
    return 32 + math.ceil(8 * 0.5 / pass_fraction) * halvings


@dataclass(frozen=True)
class PassReport:
    """What one pass did: its index, splats before and after, candidate edges."""

    index: int
    count_before: int
    count_after: int
    edges: int


def check_index_limits(splat_count: int, k: int, limit: int | None = None) -> None:
    """Refuses a scene whose kNN graph would not fit int32 indices: N k neighbour slots must be
    below ``limit`` (default INDEX_LIMIT, 2^31). The message says how many splats fit at this k."""
    limit = INDEX_LIMIT if limit is None else limit
    slots = splat_count * k
    if slots >= limit:
        fits = (limit - 1) // k
        raise InputError(
            f"{splat_count:,} splats x {k} neighbours = {slots:,} neighbour slots, more than the {limit - 1:,} "
            f"that 32-bit indices address: at k = {k} at most {fits:,} splats fit (a smaller --k fits more; "
            f"or split the scene)"
        )


def without_vertex_indexed(layout: PlyLayout | None) -> PlyLayout | None:
    """``layout`` without the other elements that index vertices (``PlyLayout.without_vertex_indexed``),
    with a one-line warning naming them; ``layout`` itself when it has none."""
    if layout is None:
        return None
    kept, dropped = layout.without_vertex_indexed()
    if dropped is not None:
        warnings.warn(f"{dropped}: they index vertices, which simplification renumbers", NanogsWarning, stacklevel=3)
    return kept


def simplify_progressively(
    splats: SplatSet,
    targets: Sequence[int],
    config: SimplifyConfig = SimplifyConfig(),
    on_pass: Callable[[PassReport], None] | None = None,
    clock: StageClock | None = None,
    finish: Callable[[SplatSet, wp.array | None], SplatSet] | None = None,
) -> Iterator[tuple[int, SplatSet]]:
    """Yields (target, splats) for each target count, largest first, continuing one progressive merge.

    Every yielded splat set has exactly ``target`` splats and stays on ``splats.device``; none of
    them, nor the input, is changed afterwards. ``clock`` (benchmarks) records per-stage times.
    ``finish`` (the fits of ``nanogs_warp.simplify_progressively``) makes each yielded set from
    the merged one, called as ``finish(merged, marks)``: ``marks`` an int32 array on the device, 1
    in each row that a merge made and 0 in each that is one of the input's splats as it was (None
    when no row was merged); the merging goes on from the merged one.
    """
    check_arguments(splats, config)
    if isinstance(targets, (str, bytes)):  # its characters would read as digits
        raise InputError(f"targets must be whole numbers, got {targets!r}")
    targets = sorted(set(whole_count(t) for t in targets), reverse=True)
    if not targets or targets[-1] < 1 or targets[0] > splats.count:
        raise InputError(f"target counts must be between 1 and the input's {splats.count} splats, got {targets}")
    cost = COSTS[config.cost](config.lambda_geo, config.lambda_app, config.samples, config.seed)
    if isinstance(cost, FieldCost):
        cost = dataclasses.replace(cost, operator=config.operator)  # it scores the operator's own merge
    merge = OPERATORS[config.operator]()

    stage = clock.stage if clock is not None else no_clock

    with stage("prune"):
        current = prune_low_opacity(splats, config.prune_opacity, keep_at_least=targets[0])
    renumbered_layout = None  # the layout of outputs whose rows are not the input's
    topology = KnnTopology(config.neighbours(current.count))
    check_index_limits(current.count, min(topology.k, max(current.count - 1, 0)))
    pass_index = 0
    marks = None  # with ``finish``: which rows merges made (``merged_rows_after``)
    # Termination: every pass removes at least one splat (or the run stops with an error), so the
    # loops end after at most count - targets[-1] passes; pass_limit stops a run long before that.
    # (the median cost limit keeps at least half of a pass's pairs: at worst half the pace; a pass
    # stops at the next budget, so each budget may add one pass)
    pace = config.pass_fraction / 2 if config.median_cost_factor > 0 else config.pass_fraction
    most_passes = pass_limit(current.count, targets[-1], pace) + len(targets)
    for target in targets:
        while current.count > target:
            if pass_index >= most_passes:
                raise RuntimeError(
                    f"simplification stopped: {pass_index} passes without reaching {target} splats "
                    f"(at {current.count}; at most {most_passes} expected from {splats.count})"
                )
            if clock is not None:
                clock.next_pass()
            n = current.count
            edges = topology(current, stage)  # times its own steps: "knn" and "edges"
            with stage("cost"):
                costs = cost(current, edges, pass_index)
            edge_count = edges.count
            with stage("pairing"):
                cap = min(n - target, max(1, math.ceil(config.pass_fraction * n)))
                pairs = select_pairs(edges, costs, n, cap=cap)
                if config.median_cost_factor > 0:
                    pairs = cheap_pairs(pairs, config.median_cost_factor)
                del edges, costs
            if pairs.count == 0:  # cannot happen with n >= 2 (a kNN graph has edges); guards the loop
                raise RuntimeError(f"simplification stopped: pass {pass_index + 1} merged nothing at {n} splats (target {target})")
            with stage("compaction"):
                merged, destination, keep = remove_rows(current, pairs.j, pairs.count)
                if finish is not None:
                    marks = merged_rows_after(marks, keep, destination, pairs.i, pairs.count, merged.count)
            with stage("merge"):
                merge(current, pairs, merged, destination)
            if on_pass is not None:
                on_pass(PassReport(pass_index, n, merged.count, edge_count))
            current = merged
            del pairs, destination, keep, merged  # free this pass's scratch before the next kNN
            pass_index += 1
        if current is not splats:  # pruned or merged: rows renumbered
            if renumbered_layout is None:
                renumbered_layout = without_vertex_indexed(splats.layout)
            if renumbered_layout is not current.layout:
                current = replace(current, layout=renumbered_layout)
        yield target, (current if finish is None else finish(current, marks))


def whole_count(c) -> int:
    """A splat count given to the API: a whole number (an int, or a float such as 5.0); InputError
    for a bool, a string, a fraction or a value that is not finite."""
    if isinstance(c, bool) or not (isinstance(c, numbers.Integral) or isinstance(c, numbers.Real) and finite(c) and int(c) == c):
        raise InputError(f"count must be a whole number, got {c!r}")
    return int(c)


def check_arguments(splats, config) -> None:
    """A TypeError where the splat set or the configuration handed to the API is something else."""
    if not isinstance(splats, SplatSet):
        raise TypeError(f"expected a SplatSet (nanogs_warp.load_ply reads one from a file), got {type(splats).__name__}")
    if not isinstance(config, SimplifyConfig):
        raise TypeError(f"config must be a SimplifyConfig (e.g. SimplifyConfig(k=16)), got {type(config).__name__}")
    config.validate()


def simplify(
    splats: SplatSet,
    ratio: float | str | Sequence[float | str] | None = None,
    count: int | Sequence[int] | None = None,
    device=None,
    config: SimplifyConfig = SimplifyConfig(),
    *,
    ratios: Sequence[float | str] | None = None,
    counts: Sequence[int] | None = None,
    finish: Callable[[SplatSet, wp.array | None], SplatSet] | None = None,
) -> SplatSet | list[SplatSet]:
    """Simplifies ``splats`` to ``count`` splats, or to max(1, ceil(ratio * N)) (exactly: the ratio
    as written, a float through its shortest repr).

    Several budgets (``ratio=[0.1, 0.01]``, ``ratios=...``, ``count=[5000, 500]`` or ``counts=...``)
    continue one progressive merge, as the command line does, and give a list of splat sets in the
    order the budgets were given. ``device`` is where the work runs ("auto", "cpu", "cuda",
    "cuda:0", a ``wp.Device``; None: the splats' own device); the results stay there. A device that
    is not on this machine raises InputError. ``finish``: as ``simplify_progressively``'s.
    """
    if ratios is not None:
        if ratio is not None:
            raise InputError("give ratio or ratios, not both")
        ratio = budget_list(ratios, "ratios")
    if counts is not None:
        if count is not None:
            raise InputError("give count or counts, not both")
        count = budget_list(counts, "counts")
    check_arguments(splats, config)
    if (ratio is None) == (count is None):
        raise InputError("give exactly one of ratio or count")
    given = scalar(ratio if ratio is not None else count)
    several = not isinstance(given, (str, numbers.Number))
    budgets = budget_list(given, "ratio" if ratio is not None else "count")
    if not budgets:
        raise InputError("give at least one budget")
    if ratio is not None:
        targets = [target_count(splats.count, r) for r in budgets]
    else:
        targets = [whole_count(c) for c in budgets]
    on_device = splats.to(device if device is not None else splats.device)  # a name read as --device reads it
    results = dict(simplify_progressively(on_device, targets, config, finish=finish))
    outputs, given_out = [], set()
    for t in targets:  # never the caller's own set, and a budget given twice gets a copy of its own
        outputs.append(results[t].clone() if results[t] is splats or t in given_out else results[t])
        given_out.add(t)
    return outputs if several else outputs[0]


def scalar(value):
    """A 0-d NumPy array as the NumPy scalar it holds (a float32 keeps its own shortest repr, which
    ``target_count`` reads), NumPy's bool as Python's; anything else as it is."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    return bool(value) if isinstance(value, np.bool_) else value


def budget_list(value, name: str) -> list:
    """The budgets of ``ratio``/``ratios``/``count``/``counts``: one number or string is one budget
    (``ratios="0.1"`` is not three of them), anything else is iterated; InputError for bytes and for
    values that are neither."""
    value = scalar(value)
    if isinstance(value, (bytes, bytearray)) or not isinstance(value, (str, numbers.Number)) and not hasattr(value, "__iter__"):
        raise InputError(f"{name} must be a number, a string or a list of them, got {type(value).__name__}")
    if isinstance(value, (str, numbers.Number)):
        return [value]
    if isinstance(value, (Set, Mapping)):  # the results come in the budgets' order, which a set has not
        raise InputError(f"{name} must be a list or tuple of budgets (the results come in their order), got {type(value).__name__}")
    return [scalar(v) for v in value]
