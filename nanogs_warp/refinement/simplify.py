"""The simplification as the package offers it (``nanogs_warp.simplify``, the command line, ``batch``):
the pipeline's progressive merge (``nanogs_warp.pipeline``), each output then fitted for size
(``size_fit``) where the configuration asks for it, as the default does."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

from ..config import SimplifyConfig
from ..device import device_lock
from ..kernel_cache import simplify_modules, use_shipped_kernels
from ..pipeline import PassReport, check_arguments
from ..pipeline import simplify as simplify_merged
from ..pipeline import simplify_progressively as merged_progressively
from ..splats import SplatSet
from ..timing import StageClock
from .size_fit import size_fit_for


def simplify_progressively(
    splats: SplatSet,
    targets: Sequence[int],
    config: SimplifyConfig = SimplifyConfig(),
    on_pass: Callable[[PassReport], None] | None = None,
    clock: StageClock | None = None,
) -> Iterator[tuple[int, SplatSet]]:
    """Yields (target, splats) for each target count, largest first, from one progressive merge
    (``pipeline.simplify_progressively``), each output fitted for size when ``config.fit_size``."""
    check_arguments(splats, config)
    use_shipped_kernels(splats.device, simplify_modules(config))  # as the commands load them: no compile where they ship
    return _one_step_at_a_time(merged_progressively(splats, targets, config, on_pass, clock, finish=size_fit_for(splats, config)),
                               splats.device)  # fmt: skip


def _one_step_at_a_time(steps: Iterator, device) -> Iterator:
    """``steps``, each one made holding ``device_lock(device)`` (released while the caller has it)."""
    while True:
        with device_lock(device):
            try:
                step = next(steps)
            except StopIteration:
                return
        yield step


def simplify(
    splats: SplatSet,
    ratio: float | str | Sequence[float | str] | None = None,
    count: int | Sequence[int] | None = None,
    device=None,
    config: SimplifyConfig = SimplifyConfig(),
    *,
    ratios: Sequence[float | str] | None = None,
    counts: Sequence[int] | None = None,
) -> SplatSet | list[SplatSet]:
    """``pipeline.simplify`` (budgets, devices and errors as documented there), each output fitted
    for size when ``config.fit_size``."""
    check_arguments(splats, config)
    on_device = splats.to(device if device is not None else splats.device)  # a name read as --device reads it
    use_shipped_kernels(on_device.device, simplify_modules(config))
    with device_lock(on_device.device):  # a program's threads: one call at a time on a device
        return simplify_merged(on_device, ratio, count, None, config, ratios=ratios, counts=counts,
                               finish=size_fit_for(on_device, config))  # fmt: skip
