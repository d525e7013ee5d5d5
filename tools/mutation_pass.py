"""A mutation pass over the kernels: does the test suite notice a one-token change?

Each mutant replaces one token inside one function of a kernel module (``>=`` -> ``>``, ``+`` -> ``-``,
a constant off by one, swapped indices, ...), runs the test files that cover that module
(``pytest -x -q``), restores the file and records whether a test failed (caught) or every test still
passed (survived). A mutant whose function or token is not in the file (the code moved on) is skipped
and reported as such. The source is restored after every mutant, also on Ctrl-C.

    python tools/mutation_pass.py                      # every mutant, from the repository root
    python tools/mutation_pass.py --root path/to/repo --only prune,pairing --json report.json
    python tools/mutation_pass.py --list               # the mutants, without running anything

Run it on a checkout nobody else is using at the same time: the kernel files are edited in place.
With the package installed in editable mode, the tests import the mutated source.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

# The test files that cover each kernel module (paths from the repository root).
TESTS = {
    "prune": ["tests/test_prune.py", "tests/test_pipeline.py"],
    "pairing": ["tests/test_pairing.py"],
    "merge": ["tests/test_merge.py", "tests/test_operators_area.py"],
    "cost": ["tests/test_cost.py"],
    "knn": ["tests/test_topology.py"],
    "edges": ["tests/test_topology.py"],
    "compact": ["tests/test_compact.py", "tests/test_pipeline.py", "tests/test_prune.py"],
    "splat_math": ["tests/test_merge.py", "tests/test_cost.py", "tests/test_operators_area.py", "tests/test_degenerate.py"],
    "portable_math": ["tests/test_portable_math.py"],
}


@dataclass(frozen=True)
class Mutant:
    """Replace the ``occurrence``-th (0-based) ``old`` inside function ``function`` of kernels/<module>.py."""

    module: str
    function: str
    old: str
    new: str
    occurrence: int = 0

    @property
    def name(self) -> str:
        suffix = f" #{self.occurrence}" if self.occurrence else ""
        return f"{self.module}.{self.function}: {self.old!r} -> {self.new!r}{suffix}"


# Changes once tried and left out because no input can tell them apart from the original
# (equivalent mutants): ``priority``'s shift 32 -> 31 (edge indices stay below 2^31, so the key's
# order is unchanged); ``bucket_of_edges``' ``splitters[mid] <= key`` -> ``<`` (keys equal to a
# splitter go to the bucket below instead: any split whose bucket grows with the key keeps rank
# order); the sequential matching's ``partner[j] = i`` -> ``partner[j] = j`` (partner
# is only read as "is free"); the coverage operator's ``ratio = ratio / grow`` -> ``ratio`` is one only for
# growth <= 1, and the tests now also run growth 2; ``log64``'s small-|f| branch test ``< 3`` -> ``< 2``
# (x within 2^-20 above a power of two then takes the general path, which rounds those the same).
# Two listed mutants are expected to survive, as they change speed, not results: ``_box_distance``
# with min for max only loosens the kNN search's pruning bound (the result stays exact), and
# ``_classify_rows``' ``j >= i`` differs from ``j > i`` only for j == i, which a kNN row never holds.
MUTANTS = [
    # pruning
    Mutant("prune", "keep_at_least", ">= threshold", "> threshold"),
    Mutant("prune", "keep_at_least", "1, 0", "0, 1"),
    Mutant("prune", "activated_opacity", "sigmoid64(wp.float64(logits[i]))", "sigmoid64(-wp.float64(logits[i]))"),
    Mutant("prune", "activated_opacity", "a = wp.float32(sigmoid64", "a = wp.float32(wp.float64(0.5) * sigmoid64"),
    Mutant("prune", "keep_rows", "first + wp.tid()", "first + wp.tid() - 1"),
    # pairing
    Mutant("pairing", "cost_order", "bits | SIGN_BIT", "bits"),
    Mutant("pairing", "cost_order", "return ~bits", "return bits"),
    Mutant("pairing", "priority", "wp.uint64(32)", "wp.uint64(16)"),
    Mutant("pairing", "both_free", "partner[i] < 0 and", "partner[i] <= 0 and"),
    Mutant("pairing", "both_free", " and ", " or "),
    Mutant("pairing", "bucket_of_edges", "splitters[mid] <= key", "splitters[mid] >= key"),
    Mutant("pairing", "bucket_counts", "counts[c, bucket[e]] += 1", "counts[c, 0] += 1"),
    Mutant("pairing", "buckets_to_sort", "slots[c, b] = slot + 1", "slots[c, b] = slot"),
    Mutant("pairing", "greedy_pairs_in_rank_order", "taken >= cap", "taken > cap", 1),
    Mutant("pairing", "greedy_pairs_in_rank_order", "bucket_start[b] + bucket_count[b]", "bucket_start[b] + bucket_count[b] - 1"),
    Mutant("pairing", "greedy_pairs_in_rank_order", "partner[i] = j", "partner[i] = -1"),
    Mutant("pairing", "accept_mutual_claims", "best[i] == key and best[j] == key", "best[i] == key or best[j] == key"),
    Mutant("pairing", "claim_endpoints", "wp.atomic_min(best, edge_j[e], key)", "wp.atomic_max(best, edge_j[e], key)"),
    Mutant("pairing", "first_pairs_by_rank", "pair_j[p] = edge_j[e]", "pair_j[p] = edge_i[e]"),
    # merge
    Mutant("merge", "over_opacity_logit", "log_sigmoid(-wp.float64(logit_j))", "log_sigmoid(wp.float64(logit_j))"),
    Mutant("merge", "blend_rows", "(wp.float64(1.0) - pi)", "(wp.float64(1.0) + pi)"),
    Mutant("merge", "blend_rows", "values[j, c]", "values[i, c]"),
    Mutant("merge", "store_gaussian", "wp.float64(0.5) * log64", "wp.float64(0.25) * log64"),
    Mutant("merge", "logit_of_log_alpha", "log_alpha < wp.float64(0.0)", "log_alpha <= wp.float64(-1.0)"),
    Mutant("merge", "log_area", "wp.float64(log_scale[1]) + wp.float64(log_scale[2])", "wp.float64(log_scale[1]) + wp.float64(log_scale[1])"),
    Mutant("merge", "log_footprint", "wp.max(a, wp.max(b, c))", "wp.max(a, b)"),
    Mutant("merge", "projected_footprint", "a00 * a11 - a01 * a01", "a00 * a11 + a01 * a01"),
    Mutant("merge", "area_weighted_moment_matching", "log_w_i - log_sigmoid(log_w_i - log_w_j)", "log_w_i + log_sigmoid(log_w_i - log_w_j)"),
    Mutant("merge", "coverage_moment_matching", "ratio > wp.float64(1.0)", "ratio > wp.float64(2.0)"),
    Mutant("merge", "coverage_moment_matching", "values[1] * grow, values[2]", "values[1] * grow, values[2] * grow"),
    Mutant("merge", "coverage_moment_matching", "ratio = ratio / grow", "ratio = ratio"),
    Mutant("merge", "mass_preserving_moment_matching", "row = int(destination[i])", "row = int(destination[j])"),
    # shared float64 geometry
    Mutant("splat_math", "moment_match", "d_j = mu_j - mu_m", "d_j = mu_i - mu_m"),
    Mutant("splat_math", "first_weight", "log_w_j - log_w_i", "log_w_i - log_w_j"),
    Mutant("splat_math", "rotation_matrix", "two * (x * y - w * z)", "two * (x * y + w * z)"),
    Mutant("splat_math", "axis_variances", "wp.max(v2, floor)", "v2"),
    Mutant("splat_math", "axis_variances", "RIDGE * ((v0 + v1) + v2)", "RIDGE * ((v0 + v1) - v2)"),
    Mutant("splat_math", "moment_match", "pi * wp.dot(d_i, d_i) + pj", "pi * wp.dot(d_i, d_j) + pj"),
    Mutant("splat_math", "frame_covariance", "u1 * r[b, 1]", "u1 * r[a, 1]"),
    # portable transcendental functions
    Mutant("portable_math", "exp64", "hi = x - t * LN2_HI", "hi = x + t * LN2_HI"),
    Mutant("portable_math", "exp64", "if x > EXP_OVERFLOW:", "if x > EXP_OVERFLOW - wp.float64(1.0):"),
    Mutant("portable_math", "scale_by_power_of_two", "wp.int64(k + 1000)", "wp.int64(k + 999)"),
    Mutant("portable_math", "log64", "k += i >> 20", "k += i >> 21"),
    Mutant("portable_math", "log64", "x = x * TWO_54", "x = x * TWO_54 * wp.float64(2.0)"),
    Mutant("portable_math", "_cos_kernel", "wp.abs(x) < wp.float64(0.3)", "wp.abs(x) < wp.float64(0.8)"),
    Mutant("portable_math", "cos_two_pi", "v > wp.float64(0.125)", "v > wp.float64(0.2)"),
    Mutant("portable_math", "normal_from_uniforms", "wp.float64(-2.0) * log64(u)", "wp.float64(-2.0) * log64(u + RANDN_OFFSET)"),
    # cost
    Mutant("cost", "runnalls_costs", "(one - pi) * log_dets[j]", "(one + pi) * log_dets[j]"),
    Mutant("cost", "runnalls_splat_terms", "log_dets[i] = log_det_axes(variances)", "log_dets[i] = log_det_axes(variances) * wp.float64(0.5)"),
    Mutant("cost", "log_det_positive", "- (e21 / d1) * e21", "+ (e21 / d1) * e21"),
    Mutant("cost", "mixture_divergence", "x = mu_j + rot_j * wp.cw_mul(z, sd_j)", "x = mu_j + rot_j * wp.cw_mul(z, sd_i)"),
    Mutant("cost", "runnalls_costs", "wp.float64(4.0) * pi", "wp.float64(2.0) * pi"),
    Mutant("cost", "finite_cost", "if not wp.isfinite(out)", "if wp.isfinite(out)"),
    Mutant("cost", "mse_costs", "wp.dot(d, d) + frob", "wp.dot(d, d) - frob"),
    # compaction
    Mutant("compact", "gather_rows", "if keep[i] == 0", "if keep[i] != 0"),
    Mutant("compact", "gather_rows", "out.log_scales[d] = src.log_scales[i]", "out.log_scales[d] = src.log_scales[d]"),
    # kNN graph and edges (pattern-based: skipped where the code has changed)
    Mutant("knn", "neighbour_key", "wp.int64(32)", "wp.int64(31)"),
    Mutant("knn", "partial_boxes", "count += 1", "count += 2"),
    Mutant("knn", "partial_boxes", "range(t, points.shape[0], parts)", "range(t + 1, points.shape[0], parts)"),
    Mutant("knn", "merged_box", "wp.max(part_hi, hi[p])", "wp.max(part_hi, lo[p])"),
    Mutant("knn", "_box_distance", "wp.max(lo - p, p - hi)", "wp.min(lo - p, p - hi)"),
    Mutant("edges", "_classify_rows", "wp.where(j > i, 1, 0)", "wp.where(j >= i, 1, 0)"),
    Mutant("edges", "row_lists", "<= reach[j]", "< reach[j]"),
    Mutant("edges", "_place_foreign", "wp.atomic_sub(count, j, 1) - 1", "wp.atomic_sub(count, j, 1)"),
]


def function_span(source: str, function: str) -> tuple[int, int] | None:
    """[start, end) of ``def function(`` through the line before the next top-level statement."""
    match = re.search(rf"^def {re.escape(function)}\(", source, flags=re.MULTILINE)
    if match is None:
        return None
    body = source.index("\n", match.end()) + 1  # the signature may span lines: they are indented or ")"
    following = re.search(r"^(?=[^\s#)])", source[body:], flags=re.MULTILINE)
    end = body + following.start() if following else len(source)
    return match.start(), end


def code_positions(source: str, start: int, end: int, token: str):
    """Where ``token`` occurs in source[start:end] outside docstrings and comments."""
    docstrings = [(m.start(), m.end()) for m in re.finditer(r'"""(?:.|\n)*?"""', source)]
    at = source.find(token, start, end)
    while at >= 0:
        line_start = source.rfind("\n", 0, at) + 1
        in_comment = "#" in source[line_start:at]
        in_docstring = any(a <= at < b for a, b in docstrings)
        if not (in_comment or in_docstring):
            yield at
        at = source.find(token, at + 1, end)


def apply(source: str, mutant: Mutant) -> str | None:
    """The mutated source, or None when the function or the token (in code) is missing."""
    span = function_span(source, mutant.function)
    if span is None:
        return None
    positions = list(code_positions(source, *span, mutant.old))
    if len(positions) <= mutant.occurrence:
        return None
    at = positions[mutant.occurrence]
    return source[:at] + mutant.new + source[at + len(mutant.old) :]


def run_tests(root: Path, files: list[str], timeout: float) -> tuple[str, float]:
    """'caught' when a test fails (or the run times out), 'survived' when all pass."""
    started = time.perf_counter()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *files],
            cwd=root,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            timeout=timeout,
        )
        outcome = "survived" if done.returncode == 0 else "caught"
    except subprocess.TimeoutExpired:
        outcome = "caught"  # a hang is noticed too
    return outcome, time.perf_counter() - started


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parent.parent, help="repository root")
    parser.add_argument("--only", help="comma-separated kernel modules (prune, pairing, ...) or module.function names")
    parser.add_argument("--json", type=Path, help="write the report as JSON to this file")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per mutant's test run (a hang counts as caught)")
    parser.add_argument("--list", action="store_true", help="list the mutants and exit")
    args = parser.parse_args(argv)

    mutants = MUTANTS
    if args.only:
        wanted = {m.strip() for m in args.only.split(",")}
        mutants = [m for m in mutants if m.module in wanted or f"{m.module}.{m.function}" in wanted]
    if args.list:
        for m in mutants:
            print(m.name)
        return 0

    signal.signal(signal.SIGTERM, _interrupt)  # restore the source on kill too
    results = []
    for number, mutant in enumerate(mutants, 1):
        path = args.root / "kernels" / f"{mutant.module}.py"
        original = path.read_text()
        mutated = apply(original, mutant)
        if mutated is None:
            outcome, seconds = "skipped", 0.0
        else:
            try:
                path.write_text(mutated)
                outcome, seconds = run_tests(args.root, TESTS[mutant.module], args.timeout)
            finally:
                path.write_text(original)
        results.append({"mutant": mutant.name, "module": mutant.module, "outcome": outcome, "seconds": round(seconds, 1)})
        print(f"[{number}/{len(mutants)}] {outcome:8s} {seconds:6.1f} s  {mutant.name}", flush=True)

    tally = {o: sum(r["outcome"] == o for r in results) for o in ("caught", "survived", "skipped")}
    print(f"caught {tally['caught']}, survived {tally['survived']}, skipped {tally['skipped']} of {len(results)}")
    for r in results:
        if r["outcome"] == "survived":
            print(f"  survived: {r['mutant']}")
    if args.json:
        args.json.write_text(json.dumps({"tally": tally, "mutants": results}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
