"""The NanoGS simplification loop (Algorithm 1): prune, then pass after pass
kNN graph -> edge costs -> disjoint greedy pairs -> merge, until the target count."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import warp as wp

from .compact import remove_rows
from .cost import COSTS
from .errors import InputError
from .operators import OPERATORS
from .pairing import select_pairs
from .prune import prune_low_opacity
from .splats import SplatSet
from .timing import StageClock, no_clock
from .topology import KnnTopology


# Neighbours per splat when k is not set: more for small scenes, where they are cheap (docs/quality.md:
# the one shared scene below the threshold, 4,721 splats, needs 24 at rho = 0.1 to beat the top-k
# baseline; the four above it, 91k to 500k splats, measure the same mean PSNR at 16 and 24, and 16 is
# about 1.3x faster). The measurements put the threshold anywhere from 4,722 to 90,854 splats.
SMALL_SCENE_SPLATS = 65_536
K_SMALL_SCENE = 24
K_LARGE_SCENE = 16


@dataclass(frozen=True)
class SimplifyConfig:
    """Every constant of the method.

    The defaults are the configuration with the best measured mean PSNR over the shared scenes and
    budgets (docs/quality.md): the coverage merge operator, the Runnalls cost, no opacity pruning
    and k = None: 24 neighbours below 65,536 splats, 16 from there on. ``SimplifyConfig.paper()`` is
    the NanoGS paper's configuration.
    """

    k: int | None = None
    prune_opacity: float = 0.0
    samples: int = 1
    seed: int = 0
    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    cost: str = "runnalls"
    operator: str = "coverage"

    @staticmethod
    def paper(**overrides) -> SimplifyConfig:
        """The paper's configuration: MPMM, Monte Carlo I-divergence, pruning at 0.1, k = 16."""
        return SimplifyConfig(**{"k": 16, "prune_opacity": 0.1, "cost": "idiv", "operator": "mpmm", **overrides})

    def neighbours(self, splat_count: int) -> int:
        """k for a scene of ``splat_count`` splats (after pruning): k itself, or when unset 24 below
        SMALL_SCENE_SPLATS splats and 16 from there on."""
        if self.k is not None:
            return self.k
        return K_SMALL_SCENE if splat_count < SMALL_SCENE_SPLATS else K_LARGE_SCENE

    def validate(self) -> None:
        if self.k is not None and not 1 <= self.k <= KnnTopology.MAX_K:
            raise InputError(f"--k must be between 1 and {KnnTopology.MAX_K}, got {self.k}")
        if not 0.0 <= self.prune_opacity <= 1.0:
            raise InputError(f"--prune-opacity must be in [0, 1], got {self.prune_opacity}")
        if not 1 <= self.samples <= 1024:
            raise InputError(f"--samples must be between 1 and 1024, got {self.samples}")
        if self.cost not in COSTS:
            raise InputError(f"unknown cost {self.cost!r}; choose one of {', '.join(COSTS)}")
        if self.operator not in OPERATORS:
            raise InputError(f"unknown operator {self.operator!r}; choose one of {', '.join(OPERATORS)}")
        for name in ("lambda_geo", "lambda_app"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number >= 0, got {value}")


def pass_limit(start_count: int, target: int) -> int:
    """Most passes a run from ``start_count`` splats down to ``target`` may take before it is
    stopped as stuck. A pass pairs off a large share of the splats (greedy matching on a kNN graph
    whose every vertex has an edge: about a third or more of them in practice, at least one pair by
    construction); the bound allows an eighth of that pace, 8 passes per halving, plus 32."""
    halvings = max(0, math.ceil(math.log2(max(start_count, 1) / max(target, 1))))
    return 32 + 8 * halvings


@dataclass(frozen=True)
class PassReport:
    """What one pass did: its index, splats before and after, candidate edges."""

    index: int
    count_before: int
    count_after: int
    edges: int


def target_count(input_count: int, ratio: float) -> int:
    """N_tgt = max(1, ceil(ratio * N_0))."""
    if not (0.0 < ratio <= 1.0):
        raise InputError(f"ratio must be in (0, 1], got {ratio}")
    return max(1, math.ceil(ratio * input_count))


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
    # Termination: every pass removes at least one splat (or the run stops with an error), so the
    # loops end after at most count - targets[-1] passes; pass_limit stops a run long before that.
    most_passes = pass_limit(current.count, targets[-1])
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
                pairs = select_pairs(edges, costs, n, cap=n - target)
                del edges, costs
            if pairs.count == 0:  # cannot happen with n >= 2 (a kNN graph has edges); guards the loop
                raise RuntimeError(f"simplification stopped: pass {pass_index + 1} merged nothing at {n} splats (target {target})")
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
