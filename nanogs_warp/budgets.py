"""Budgets from the command line (--ratio / --count lists) and the output path of each."""

from __future__ import annotations

from dataclasses import dataclass, field
from decimal import Decimal, localcontext
from fractions import Fraction
from pathlib import Path

from .config import RATIO_DIGITS, RatioTooLong, exact_ratio, target_count
from .errors import InputError


@dataclass(frozen=True)
class Budget:
    """Keep a ``ratio`` of the input's splats, or an absolute ``count``.

    ``exact`` is the ratio as the user wrote it (``parse_budgets``), so that the target is
    ceil(ratio * N) exactly; without it, the float's shortest repr is used (0.07 is 7/100)."""

    ratio: float | None = None
    count: int | None = None
    exact: Fraction | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.ratio is not None and self.exact is None:  # the float's shortest repr: 0.1 is 1/10
            object.__setattr__(self, "exact", exact_ratio(self.ratio))

    @property
    def typed_apart(self) -> bool:
        """Whether the ratio as written is not the float's shortest repr (0.10000000000000001 keeps
        3 of 20 splats, 0.1 keeps 2): its label and record then carry it as written."""
        return self.ratio is not None and self.exact != exact_ratio(self.ratio)

    @property
    def exact_text(self) -> str:
        """The ratio as written, as a plain decimal (0.10000000000000001)."""
        digits = len(str(self.exact.denominator)) + len(str(self.exact.numerator)) + 2
        with localcontext() as context:
            context.prec = digits  # a decimal fraction divides exactly
            value = Decimal(self.exact.numerator) / Decimal(self.exact.denominator)
            return format(value.normalize(), "f")  # in the context: outside it, normalize() rounds to 28 digits

    @property
    def label(self) -> str:
        """The budget in output names: the ratio in at most six digits (0.1, 1e-05, 1) where that is
        the ratio itself, else in as many as it needs (0.1000001, or 0.10000000000000001 as written
        where that keeps another count than the float 0.1): different budgets never share a file
        name. Or the count."""
        if self.ratio is None:
            return str(self.count)
        if self.typed_apart:
            return self.exact_text
        short = f"{self.ratio:g}"
        return short if float(short) == self.ratio else repr(self.ratio)

    def target(self, input_count: int) -> int:
        """max(1, ceil(ratio * N0)), or the count itself; checked against the input's size."""
        if self.ratio is not None:
            return target_count(input_count, self.exact)
        if self.count > input_count:
            raise InputError(f"--count {self.count} is more than the input's {input_count} splats")
        return self.count


def parse_budgets(ratio: str | None, count: str | None) -> list[Budget]:
    """Budgets from ``--ratio 0.1,0.01`` or ``--count 5000,500`` (exactly one of the two)."""
    if (ratio is None) == (count is None):
        raise InputError("give exactly one of --ratio or --count")
    text = ratio if ratio is not None else count
    tokens = [t.strip() for t in text.split(",")]
    if not tokens or any(not t or not t.isascii() or "_" in t for t in tokens):  # Python's 1_000 is no number a user types
        raise InputError(f"cannot read budgets from {text!r}: expected comma-separated numbers")
    budgets = []
    for token in tokens:
        if ratio is not None:
            try:
                exact = exact_ratio(token)
            except RatioTooLong:
                raise InputError(f"--ratio {token!r} is longer than the {RATIO_DIGITS:,} digits a ratio may have") from None
            except InputError:
                raise InputError(f"--ratio {token!r} must be a number in (0, 1]") from None
            value = float(Decimal(token))  # as typed: exact_ratio counts every ratio below 1e-60 as 1e-61
            if value == 0.0:
                raise InputError(f"--ratio {token} is too small to use; give --count 1 instead")
            budgets.append(Budget(ratio=value, exact=exact))
        else:
            try:
                value = int(token)
            except ValueError:
                raise InputError(f"--count {token!r} is not a whole number") from None
            if value < 1:
                raise InputError(f"--count {token} must be at least 1")
            budgets.append(Budget(count=value))
    if len(set(budgets)) != len(budgets):
        raise InputError(f"the same budget is given twice in {text!r}")
    return budgets


def output_paths(output: Path, budgets: list[Budget], default_suffix: str = ".ply") -> dict[Budget, Path]:
    """One budget writes ``output`` itself; several write ``<stem>_<label><suffix>`` beside it,
    e.g. ``out.ply`` with --ratio 0.1,0.01 gives ``out_0.1.ply`` and ``out_0.01.ply`` (and
    ``out.compressed.ply`` gives ``out_0.1.compressed.ply``); a name without a suffix takes
    ``default_suffix`` (``--format``'s extension)."""
    output = Path(output)
    if len(budgets) == 1:
        return {budgets[0]: output}
    suffix = output.suffix or default_suffix
    if output.name.lower().endswith(".compressed.ply"):  # one suffix in two parts
        suffix = output.name[-len(".compressed.ply") :]
    stem = output.name[: len(output.name) - len(suffix)] if output.suffix else output.name
    return {b: output.with_name(f"{stem}_{b.label}{suffix}") for b in budgets}
