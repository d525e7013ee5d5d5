"""Budgets: ceil(ratio * N) exactly, for every ratio a user can type."""

from decimal import Decimal
from fractions import Fraction

import pytest

from nanogs_warp.budgets import parse_budgets
from nanogs_warp.errors import InputError
from nanogs_warp.pipeline import exact_ratio, target_count


def exact_target(n, text):
    value = Fraction(Decimal(text))
    return max(1, -(-n * value.numerator // value.denominator))


@pytest.mark.parametrize(
    "n, ratio, expected",
    [
        (100, 0.07, 7),  # 0.07 * 100 is 7.000000000000001 in floating point
        (100, 0.29, 29),  # 28.999999999999996
        (1000, 0.001, 1),
        (3, 1 / 3, 1),  # the float 1/3 is 0.3333333333333333 as written: 3 times that is below 1
        (10, 0.1, 1),
        (10, 0.11, 2),
        (1, 0.5, 1),
        (7, 1.0, 7),
        (123_456_789, 0.1, 12_345_679),
        (2**40, 0.5, 2**39),
        (2**53 + 1, 1.0, 2**53 + 1),
    ],
)
def test_target_count_is_exact(n, ratio, expected):
    assert target_count(n, ratio) == expected
    assert target_count(n, repr(ratio)) == expected
    assert target_count(n, Decimal(repr(ratio))) == expected


def test_every_two_decimal_ratio_of_small_scenes():
    """Every ratio 0.01 .. 1.00 on every scene of 1 .. 300 splats: integer arithmetic agrees."""
    for n in range(1, 301):
        for hundredths in range(1, 101):
            text = f"{hundredths / 100:.2f}"
            want = max(1, -(-n * hundredths // 100))
            assert target_count(n, float(text)) == want, (n, text)
            assert target_count(n, text) == want, (n, text)


@pytest.mark.parametrize("text", ["0.07", "7e-2", "0.0700", "1", "1.0", "0.333333333333333333333", "1e-9", "0.123456789012345678901234567890"])
def test_parsed_ratio_is_the_typed_decimal(text):
    (budget,) = parse_budgets(text, None)
    for n in (1, 7, 100, 999_983, 10**12 + 7):
        assert budget.target(n) == exact_target(n, text)


def test_typed_digits_beyond_a_float_count():
    """0.1000000000000000000001 is above 0.1, so 10 splats keep 2; as a float it would be 0.1 (1)."""
    (budget,) = parse_budgets("0.1000000000000000000001", None)
    assert budget.target(10) == 2
    assert target_count(10, 0.1) == 1


def test_a_ratio_written_apart_from_its_float_is_labelled_as_written():
    a, b = parse_budgets("0.1,0.10000000000000001", None)
    assert a != b and (a.label, b.label) == ("0.1", "0.10000000000000001") and b.target(20) == 3
    assert parse_budgets("7e-2", None)[0].label == "0.07" and not parse_budgets("0.0700", None)[0].typed_apart


def test_ratios_apart_beyond_28_digits_get_labels_apart():
    """Decimal's default context has 28 digits: a label normalised outside the division's own
    context named 0.1000000000000000000000000000000001 '0.1', and its output overwrote the 0.1 one."""
    a, b = parse_budgets("0.1000000000000000000000000000000001,0.1", None)
    assert (a.label, b.label) == ("0.1000000000000000000000000000000001", "0.1") and (a.target(20), b.target(20)) == (3, 2)


def test_a_ratio_of_thousands_of_digits_is_refused_before_any_work():
    """Its label spelled out the denominator, past Python's 4,300 digits of int-to-text: an
    internal error after the whole run."""
    assert len(parse_budgets("0." + "1" * 997, None)[0].label) == 999
    with pytest.raises(InputError, match="longer than the 1,000 digits"):
        parse_budgets("0." + "1" * 5000, None)
    with pytest.raises(InputError, match="at most 1,000 digits"):
        exact_ratio("0." + "1" * 1001)


def test_float_api_converts_through_its_shortest_repr():
    assert exact_ratio(0.07) == Fraction(7, 100)
    assert exact_ratio("0.07") == Fraction(7, 100)
    assert exact_ratio(Fraction(1, 3)) == Fraction(1, 3)


@pytest.mark.parametrize("bad", [0.0, -0.1, 1.0000001, float("nan"), float("inf"), "abc", "", "1/2", "０.５", "0.\u0665"])  # other scripts' digits: as --ratio
def test_bad_ratios(bad):
    with pytest.raises(InputError):
        target_count(100, bad)


@pytest.mark.parametrize("bad", ["0", "-0.5", "1.01", "nan", "inf", "x", "0.1,", "0.1,0.10"])
def test_bad_budget_text(bad):
    with pytest.raises(InputError):
        parse_budgets(bad, None)


def test_tiny_typed_ratio_keeps_one_splat():
    (budget,) = parse_budgets("1e-300", None)
    assert budget.target(10**9) == 1
    assert target_count(10**9, "1e-999999999") == 1  # no giant denominator


@pytest.mark.parametrize("huge", ["1e999999999", "9.9e999999999", "-1e999999999", "1e1", "10"])
def test_ratios_far_above_one_are_refused_before_any_arithmetic(huge):
    """A huge exponent is refused as it is read: Fraction() of it would build the integer 10^exponent
    (minutes for 1e999999999)."""
    with pytest.raises(InputError, match=r"must be a number in \(0, 1\]"):
        parse_budgets(huge, None)
    with pytest.raises(InputError):
        exact_ratio(huge)


@pytest.mark.parametrize("text", ["\u0661", "0.\u0665", "\uff11"])  # Arabic-Indic and full-width digits
def test_budgets_are_ascii_numbers(text):
    with pytest.raises(InputError, match="comma-separated numbers"):
        parse_budgets(text, None)
    with pytest.raises(InputError, match="comma-separated numbers"):
        parse_budgets(None, text)


def test_different_ratios_never_share_an_output_name():
    from pathlib import Path

    from nanogs_warp.budgets import output_paths

    budgets = parse_budgets("1,0.1,0.1000001,1e-05,0.000123456789", None)
    assert [b.label for b in budgets] == ["1", "0.1", "0.1000001", "1e-05", "0.000123456789"]
    paths = output_paths(Path("out.ply"), budgets)
    assert len(set(paths.values())) == len(budgets)
    assert paths[budgets[2]] == Path("out_0.1000001.ply")
    assert [b.label for b in parse_budgets(None, "500,50")] == ["500", "50"]
