"""Merge operators: fuse each chosen pair into one splat.

A merge operator is a callable ``operator(source, pairs, out, destination) -> None``. ``out`` is
``source`` without the rows ``pairs.j`` (row r of source is row destination[r] of out); the operator
overwrites the row of each ``pairs.i[p]`` in ``out`` with the pair's merged splat. ``source`` is
never changed. Add an operator by writing its kernel in ``nanogs_warp.kernels.merge`` and a class
here, then naming it in ``OPERATORS``.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from .kernels import merge as kernels
from .pairing import Pairs
from .parallel import launch_rows
from .splats import SplatSet


def _launch(kernel, source: SplatSet, pairs: Pairs, out: SplatSet, destination: wp.array, *parameters) -> None:
    """One thread per pair; pairs are disjoint and write distinct rows, so the CPU may split them."""
    launch_rows(
        kernel, pairs.count,
        lambda rows: [pairs.i[rows], pairs.j[rows], destination, source.kernel_view(), out.kernel_view(), *parameters],
        source.device,
        min_rows=1024,  # about 1 us a merge on a CPU core
    )  # fmt: skip


@dataclass(frozen=True)
class MassPreservingMomentMatching:
    """MPMM (NanoGS Sec. 3.3): mass-weighted moments, over-rule opacity."""

    def __call__(self, source: SplatSet, pairs: Pairs, out: SplatSet, destination: wp.array) -> None:
        _launch(kernels.mass_preserving_moment_matching, source, pairs, out, destination)


@dataclass(frozen=True)
class AreaWeightedMomentMatching:
    """Weights opacity x surface-area proxy (s0 s1 + s0 s2 + s1 s2, as hierarchical 3DGS); merged
    opacity conserving the weighted mass, clamped to (0, 1)."""

    def __call__(self, source: SplatSet, pairs: Pairs, out: SplatSet, destination: wp.array) -> None:
        _launch(kernels.area_weighted_moment_matching, source, pairs, out, destination)


# The coverage operator's growth exponent, shared with the field cost that scores its merges.
# Growth gives back the coverage a single Gaussian (alpha <= 1) loses against the flat-topped union
# of opaque splats it replaces, but pushes merged splats past sharp edges. Chosen by
# leave-one-scene-out over the eight shared and four generated stress scenes with the field cost
# (docs/quality.md): 0.5 in eleven of twelve folds; against 0.25 the worst gap to the best other
# tool (or to the paper's configuration on a stress scene) goes from -3.25 to -2.11 dB and the
# mean gap from +1.33 to +1.21 dB, with halos along sharp edges at 1 % and below (statue
# -0.6 / -1.2 dB) and 0.75 and 1 far worse on every converted mesh.
COVERAGE_GROWTH = 0.5


@dataclass(frozen=True)
class CoverageMomentMatching:
    """Weights opacity x face-on footprint; merged opacity conserving the pair's coverage in the
    merged splat's face plane; where alpha would exceed 1, the face plane grows by
    (coverage / footprint)^growth first (0: never grow, 1: always keep all coverage).

    ``growth`` is ``COVERAGE_GROWTH`` and not a command-line option: it is a measured constant of
    the default operator. Python callers may still build ``CoverageMomentMatching(growth=...)`` to
    experiment (the field cost's ``FieldCost.growth`` must then match)."""

    growth: float = COVERAGE_GROWTH

    def __call__(self, source: SplatSet, pairs: Pairs, out: SplatSet, destination: wp.array) -> None:
        _launch(kernels.coverage_moment_matching, source, pairs, out, destination, float(self.growth))


OPERATORS = {
    "mpmm": MassPreservingMomentMatching,
    "area": AreaWeightedMomentMatching,
    "coverage": CoverageMomentMatching,
}
