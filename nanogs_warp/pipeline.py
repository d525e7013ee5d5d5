"""The NanoGS simplification loop (Algorithm 1): prune, then pass after pass
kNN graph -> edge costs -> disjoint greedy pairs -> merge, until the target count."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import warp as wp

from .compact import remove_rows
from .config import K_LARGE_SCENE, K_SMALL_SCENE, SMALL_SCENE_SPLATS, SimplifyConfig, target_count  # noqa: F401
from .cost import COSTS
from .errors import InputError
from .operators import OPERATORS
from .pairing import select_pairs
from .prune import prune_low_opacity
from .splats import SplatSet
from .timing import StageClock, no_clock
from .topology import KnnTopology


@dataclass(frozen=True)
class PassReport:
    """What one pass did: its index, splats before and after, candidate edges."""

    index: int
    count_before: int
    count_after: int
    edges: int


def simplify_progressively(
    splats: SplatSet,
    targets: Sequence[int],
    config: SimplifyConfig = SimplifyConfig(),
    on_pass: Callable[[PassReport], None] | None = None,
    clock: StageClock | None = None,
) -> Iterator[tuple[int, SplatSet]]:
    """Yields (target, splats) for each target count, largest first, continuing one progressive merge.

    Every yielded splat set has exactly ``target`` splats and stays on ``splats.device``; none of
    them, nor the input, is changed afterwards. ``clock`` (benchmarks) records per-stage times.
    """
    config.validate()
    targets = sorted(set(int(t) for t in targets), reverse=True)
    if not targets or targets[-1] < 1 or targets[0] > splats.count:
        raise InputError(f"target counts must be between 1 and the input's {splats.count} splats, got {targets}")
    cost = COSTS[config.cost](config.lambda_geo, config.lambda_app, config.samples, config.seed)
    merge = OPERATORS[config.operator]()

    stage = clock.stage if clock is not None else no_clock

    with stage("prune"):
        current = prune_low_opacity(splats, config.prune_opacity, keep_at_least=targets[0])
    topology = KnnTopology(config.neighbours(current.count))
    pass_index = 0
    for target in targets:
        while current.count > target:
            if clock is not None:
                clock.next_pass()
            n = current.count
            edges = topology(current, stage)  # times its own steps: "knn" and "edges"
            with stage("cost"):
                costs = cost(current, edges, pass_index)
            edge_count = edges.count
            with stage("pairing"):
                pairs = select_pairs(edges, costs, n, cap=n - target)
                del edges, costs
            if pairs.count == 0:  # cannot happen with n >= 2 (a kNN graph has edges); guards the loop
                raise RuntimeError(f"no merge possible at {n} splats")
            with stage("compaction"):
                merged, destination = remove_rows(current, pairs.j, pairs.count)
            with stage("merge"):
                merge(current, pairs, merged, destination)
            if on_pass is not None:
                on_pass(PassReport(pass_index, n, merged.count, edge_count))
            current = merged
            del pairs, destination, merged  # free this pass's scratch before the next kNN
            pass_index += 1
        yield target, current


def simplify(
    splats: SplatSet,
    ratio: float | None = None,
    count: int | None = None,
    device=None,
    config: SimplifyConfig = SimplifyConfig(),
) -> SplatSet:
    """Simplifies ``splats`` to ``count`` splats, or to max(1, ceil(ratio * N)).

    ``device`` is where the work runs ("cpu", "cuda:0", ...; None: the splats' own device); the
    result stays there.
    """
    if (ratio is None) == (count is None):
        raise InputError("give exactly one of ratio or count")
    target = target_count(splats.count, ratio) if ratio is not None else int(count)
    on_device = splats.to(wp.get_device(device) if device is not None else splats.device)
    _, result = next(simplify_progressively(on_device, [target], config))
    return result
