"""The method's settings (:class:`SimplifyConfig`, named presets) and the target count of a ratio,
without Warp: the command line reads them before it decides whether it needs Warp at all."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from fractions import Fraction

from .errors import InputError


def finite(value) -> bool:
    """Whether ``value`` is a finite float or converts to one: False for an integer too large for a
    float (where math.isfinite raises OverflowError)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


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

    The defaults are the configuration chosen by leave-one-scene-out over the shared scenes and
    generated stress scenes (docs/quality.md): the coverage merge operator, the field cost, at most
    45 % of the splats merged a pass and no pair above 3 times the pass's median pair cost, no
    opacity pruning, k = None: 24 neighbours below 65,536 splats, 16 from there on, and the size
    fit of every output, the geometry fit of those at or below 1 % of the input and the colour fit
    of the others.
    ``SimplifyConfig.paper()`` is the NanoGS paper's configuration (``--preset paper``).

    ``pass_fraction``: at most this fraction of the current splats merge in one pass, the cheapest
    pairs of the matching first; 0.5 takes the whole matching as the paper does, smaller values merge
    cheap regions first over more passes.

    ``median_cost_factor``: of those pairs, a pass merges none that costs more than this many times
    the median pair's cost (at least half of them always merge): a region whose merges cost far
    more than the rest waits for a later pass instead of being forced. 0 turns the limit off.

    ``fit_size``: each output has its splats' axes scaled by the one factor whose renders match the
    input's best at a coarse and at a fine pixel size (``refinement.size_fit``); the merging itself
    is unchanged.

    ``fit_geometry``: each output of at most 1 % then has its splats' centres, rotations and scales
    (not their opacity or colour) fitted to renders of the input from cameras around it, a short
    refinement (a longer one for outputs of at most 0.1 %) kept only where it renders held-out views
    of the input better (``refinement.geometry_fit``).

    ``fit_colour``: each output above 0.1 % (after its geometry fit, at 1 %) then has the colours of
    its merged splats fitted to the same renders, every splat that no merge made keeping its own,
    kept only where the output then renders the size fit's coarse and fine views better
    (``refinement.colour_fit``).
    """

    k: int | None = None
    prune_opacity: float = 0.0
    samples: int = 1
    seed: int = 0
    lambda_geo: float = 1.0
    lambda_app: float = 1.0
    cost: str = "field"
    operator: str = "coverage"
    pass_fraction: float = 0.45
    median_cost_factor: float = 3.0
    fit_size: bool = True
    fit_geometry: bool = True
    fit_colour: bool = True

    def __post_init__(self):
        self.validate()  # a bad configuration fails where it is built, not where it runs
        for name, kind in _FIELD_KINDS.items():  # NumPy's integers and floats as Python's: Warp takes those
            value = getattr(self, name)
            if kind.startswith("int") and value is not None and type(value) is not int:
                object.__setattr__(self, name, int(value))
            elif kind == "number" and type(value) is not float:
                object.__setattr__(self, name, float(value))

    @staticmethod
    def paper(**overrides) -> SimplifyConfig:
        """The paper's configuration: MPMM, Monte Carlo I-divergence, pruning at 0.1, k = 16."""
        return SimplifyConfig.preset("paper", **overrides)

    @staticmethod
    def preset(name: str, **overrides) -> SimplifyConfig:
        """A named configuration with ``overrides``: "default" (this class's defaults), "fast" or "paper"."""
        if name not in PRESETS:
            raise InputError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        return SimplifyConfig(**{**PRESETS[name], **overrides})

    def neighbours(self, splat_count: int) -> int:
        """k for a scene of ``splat_count`` splats (after pruning): k itself, or when unset 24 below
        SMALL_SCENE_SPLATS splats and 16 from there on."""
        if self.k is not None:
            return self.k
        return K_SMALL_SCENE if splat_count < SMALL_SCENE_SPLATS else K_LARGE_SCENE

    def validate(self) -> None:
        """Checks every option without importing Warp (the names below are those of the kernel
        registries, ``cost.COSTS``, ``operators.OPERATORS`` and ``topology.KnnTopology.MAX_K``)."""
        check_types(self, _FIELD_KINDS)
        if self.k is not None and not 1 <= self.k <= MAX_K:
            raise InputError(f"--k must be between 1 and {MAX_K}, got {self.k}")
        if not 0.0 <= self.prune_opacity <= 1.0:
            raise InputError(f"--prune-opacity must be in [0, 1], got {self.prune_opacity}")
        if not 1 <= self.samples <= 1024:
            raise InputError(f"--samples must be between 1 and 1024, got {self.samples}")
        if self.cost not in COST_NAMES:
            raise InputError(f"unknown cost {self.cost!r}; choose one of {', '.join(COST_NAMES)}")
        if self.operator not in OPERATOR_NAMES:
            raise InputError(f"unknown operator {self.operator!r}; choose one of {', '.join(OPERATOR_NAMES)}")
        if self.cost == "field" and self.operator not in FIELD_COST_OPERATORS:
            raise InputError(f"--cost field scores the mpmm and coverage operators, not {self.operator!r}")
        if not (MIN_PASS_FRACTION <= self.pass_fraction <= 0.5):
            raise InputError(f"--pass-fraction must be in [{MIN_PASS_FRACTION}, 0.5], got {self.pass_fraction}")
        if not (self.median_cost_factor == 0.0 or 1.0 <= self.median_cost_factor and finite(self.median_cost_factor)):
            raise InputError(f"--median-cost-factor must be 0 (no limit) or a finite number >= 1, got {self.median_cost_factor}")
        for name in ("lambda_geo", "lambda_app"):
            value = getattr(self, name)
            if not (finite(value) and value >= 0):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number >= 0, got {value}")
        if not 0 <= self.seed <= MAX_SEED:
            raise InputError(f"--seed must be between 0 and {MAX_SEED}, got {self.seed}")


MAX_SEED = 2**31 - 1  # the kernels take the seed as a 32-bit integer
# What each field of SimplifyConfig holds: "int" and "number" exclude bool.
_FIELD_KINDS = {"k": "int|None", "prune_opacity": "number", "samples": "int", "seed": "int", "lambda_geo": "number",
                "lambda_app": "number", "cost": "str", "operator": "str", "pass_fraction": "number",
                "median_cost_factor": "number", "fit_size": "bool", "fit_geometry": "bool",
                "fit_colour": "bool"}  # fmt: skip


def check_types(settings, kinds: dict[str, str]) -> None:
    """An InputError naming the first field of the dataclass ``settings`` whose value is not of its
    kind in ``kinds`` ("int", "number", "str", "bool", with "|None" where None is allowed): a
    setting of the wrong type fails where it is built, with the field's name."""
    tests = {
        "int": lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool),
        "number": lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool),
        "str": lambda v: isinstance(v, str),
        "bool": lambda v: isinstance(v, bool),
        "None": lambda v: v is None,
    }
    for name, kind in kinds.items():
        value = getattr(settings, name)
        if not any(tests[k](value) for k in kind.split("|")):
            expected = {"int": "a whole number", "number": "a number", "str": "a string", "bool": "True or False"}
            what = " or ".join(expected.get(k, k) for k in kind.split("|"))
            raise InputError(f"{type(settings).__name__}.{name} must be {what}, got {value!r}")


# The kernel registries' names, here so that a configuration is checked without importing Warp (a
# test checks them against cost.COSTS, operators.OPERATORS, FieldCost.OPERATOR_IDS and KnnTopology.MAX_K).
COST_NAMES = ("field", "idiv", "mse", "runnalls")
OPERATOR_NAMES = ("mpmm", "area", "coverage")
FIELD_COST_OPERATORS = ("mpmm", "coverage")
MAX_K = 32
# The smallest pass fraction: about 14 passes a halving of the count (2-3 at the default), so a run
# stays within a few times the default's time; a smaller one (1e-9: one merge a pass) would run for
# hours.
MIN_PASS_FRACTION = 0.05

# Named configurations (``--preset``): the measured default, the previous default (the Runnalls
# cost and whole matchings: about 3x faster on a CPU, best on the trained captures at the smaller
# budgets, worse on meshes and flat opaque content; docs/quality.md) and the NanoGS paper's own.
PRESETS: dict[str, dict] = {
    "default": {},
    "fast": {"cost": "runnalls", "pass_fraction": 0.5, "median_cost_factor": 0.0, "fit_size": False, "fit_geometry": False,
             "fit_colour": False},
    "paper": {"k": 16, "prune_opacity": 0.1, "cost": "idiv", "operator": "mpmm", "pass_fraction": 0.5, "median_cost_factor": 0.0,
              "fit_size": False, "fit_geometry": False, "fit_colour": False},
}


RATIO_DIGITS = 1000  # far past any count's need (a float has 17), well within Python's int-to-text limit


class RatioTooLong(InputError):
    """A ratio written with more than RATIO_DIGITS digits."""


def exact_ratio(ratio: float | str | Decimal | Fraction) -> Fraction:
    """The ratio as an exact fraction in (0, 1]: text ("0.07", "7e-2") and Decimals as written, a
    float as its shortest repr (0.07 is 7/100, not the binary double just below it)."""
    if isinstance(ratio, Fraction):
        value = ratio
    else:
        text = repr(float(ratio)) if isinstance(ratio, float) else str(ratio).strip()  # numpy's float64 too
        try:
            if not text.isascii():  # Decimal reads other scripts' digits ("０.５"); --ratio takes ASCII alone
                raise ValueError
            decimal = Decimal(text)
        except (InvalidOperation, ValueError):
            raise InputError(f"ratio {ratio!r} is not a number") from None
        # refused before Fraction(), which would build 10^exponent for a huge exponent ("1e999999999")
        if not decimal.is_finite() or decimal < 0 or decimal.adjusted() > 0:
            raise InputError(f"ratio must be in (0, 1], got {ratio}")
        if len(decimal.as_tuple().digits) > RATIO_DIGITS:  # its label and record spell it out as written
            raise RatioTooLong(f"a ratio may have at most {RATIO_DIGITS:,} digits; this one has {len(decimal.as_tuple().digits):,}")
        # beyond 1e-60 every scene below 1e60 splats keeps one splat: spare Fraction a huge denominator
        if decimal > 0 and decimal.adjusted() < -60:
            decimal = Decimal("1e-61")
        value = Fraction(decimal)
    if not 0 < value <= 1:
        raise InputError(f"ratio must be in (0, 1], got {ratio}")
    return value


def target_count(input_count: int, ratio: float | str | Decimal | Fraction) -> int:
    """N_tgt = max(1, ceil(ratio * N_0)), exactly: integer arithmetic on the ratio as written
    (``exact_ratio``), so target_count(100, 0.07) is 7."""
    value = exact_ratio(ratio)
    return max(1, -(-int(input_count) * value.numerator // value.denominator))
