"""Run ``nanogs-warp simplify`` and ``info`` on every case of a fuzz corpus (tools/fuzz_corpus.py),
each in its own process with a time limit, and tally what happened.

    python tools/fuzz_run.py corpus/ --device cpu --jobs 2 --clean SAMPLE.ply
    python tools/fuzz_run.py corpus/ --device cuda:0 --clean SAMPLE.ply --report fuzz-cuda.json

A case passes when each command either refuses it cleanly (exit code 2, exactly one line on stderr
starting ``nanogs-warp: error:``, no output file and no temporary file left, the input unchanged)
or succeeds with a valid result (``simplify``: exit 0, the output holds exactly the budget's count,
max(1, ceil(ratio x N)) of the N splats it read, every value finite, nothing else written;
``info``: exit 0, JSON on stdout, nothing on stderr). Anything else fails: another exit code, a
traceback or warning on stderr, a leftover file, a changed input, or running past the time limit.

The limit is --timeout seconds, or 10x the time ``simplify`` takes on --clean (a valid scene,
measured first the same way). Prints the tally per family and outcome, the failures and the
slowest cases; --report writes every result as JSON. Exit code 1 if any case failed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nanogs_warp.io.ply import read_ply_arrays
from nanogs_warp.pipeline import target_count

ERROR_PREFIX = "nanogs-warp: error: "


@dataclass
class Outcome:
    command: str
    status: str  # "refused", "valid" or "FAIL"
    seconds: float
    detail: str = ""


@dataclass
class CaseResult:
    file: str
    family: str
    what: str
    outcomes: list[Outcome] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(o.status != "FAIL" for o in self.outcomes)


def run_command(arguments: list[str], timeout: float) -> tuple[int | None, str, str, float]:
    """(exit code or None on timeout, stdout, stderr, seconds); the process group is killed on timeout."""
    start = time.perf_counter()
    process = subprocess.Popen(
        [sys.executable, "-m", "nanogs_warp", *arguments],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        out, err = process.communicate(timeout=timeout)
        return process.returncode, out, err, time.perf_counter() - start
    except subprocess.TimeoutExpired:
        try:
            import os

            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        out, err = process.communicate()
        return None, out, err, time.perf_counter() - start


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def check_refusal(code, err: str, leftovers: list[str]) -> str:
    """'' when the run refused its input the one clean way, else what was wrong."""
    lines = err.splitlines()
    if len(lines) != 1 or not lines[0].startswith(ERROR_PREFIX):
        return f"stderr is not one error line: {err[-300:]!r}"
    if "internal error" in lines[0]:
        return f"internal error: {lines[0]}"
    if leftovers:
        return f"files left behind: {leftovers}"
    return ""


def check_simplified(output: Path, summary: dict, ratio: float, leftovers: list[str]) -> str:
    """'' when the output is valid: the budget's exact count, finite values, nothing else written."""
    if leftovers != [output.name]:
        return f"files written: {leftovers}"
    arrays = read_ply_arrays(output).arrays
    n = arrays["means"].shape[0]
    expected = target_count(summary["input_count"], ratio)
    if n != expected or summary["outputs"][0]["count"] != n:
        return f"{n} splats written, {expected} expected"
    for key, values in arrays.items():
        if values.size and not np.isfinite(values).all():
            return f"non-finite {key} in the output"
    return ""


def simplify_case(path: Path, args, timeout: float) -> Outcome:
    with tempfile.TemporaryDirectory(prefix="fuzz-out-") as folder:
        output = Path(folder) / "out.ply"
        before = digest(path)
        arguments = ["simplify", str(path), "-o", str(output), "--ratio", str(args.ratio), "--device", args.device, "--json"]
        code, out, err, seconds = run_command(arguments, timeout)
        leftovers = sorted(p.name for p in Path(folder).iterdir())
        changed = digest(path) != before
        if code is None:
            return Outcome("simplify", "FAIL", seconds, f"still running after {timeout:.1f} s (killed)")
        if changed:
            return Outcome("simplify", "FAIL", seconds, "the input changed")
        if code == 2:
            problem = check_refusal(code, err, leftovers)
            return Outcome("simplify", "FAIL" if problem else "refused", seconds, problem or err.strip())
        if code != 0:
            return Outcome("simplify", "FAIL", seconds, f"exit code {code}: {err.strip()[-300:]}")
        if any(line and not line.startswith("nanogs-warp: warning: ") for line in err.strip().splitlines()):
            return Outcome("simplify", "FAIL", seconds, f"exit 0 with stderr: {err[-300:]!r}")
        try:
            problem = check_simplified(output, json.loads(out), args.ratio, leftovers)
        except Exception as e:  # noqa: BLE001 - any failure to read the output is the finding
            problem = f"output unreadable: {type(e).__name__}: {e}"
        return Outcome("simplify", "FAIL" if problem else "valid", seconds, problem)


def info_case(path: Path, timeout: float) -> Outcome:
    before = digest(path)
    code, out, err, seconds = run_command(["info", str(path), "--json"], timeout)
    if code is None:
        return Outcome("info", "FAIL", seconds, f"still running after {timeout:.1f} s (killed)")
    if digest(path) != before:
        return Outcome("info", "FAIL", seconds, "the input changed")
    if code == 2:
        problem = check_refusal(code, err, [])
        return Outcome("info", "FAIL" if problem else "refused", seconds, problem or err.strip())
    if code != 0 or err.strip():
        return Outcome("info", "FAIL", seconds, f"exit code {code}: {err.strip()[-300:]}")
    try:
        json.loads(out)
    except json.JSONDecodeError:
        return Outcome("info", "FAIL", seconds, "stdout is not JSON")
    return Outcome("info", "valid", seconds)


def clean_time(path: Path, args) -> float:
    with tempfile.TemporaryDirectory(prefix="fuzz-clean-") as folder:
        arguments = ["simplify", str(path), "-o", str(Path(folder) / "out.ply"), "--ratio", str(args.ratio),
                     "--device", args.device, "-q", "-w"]  # fmt: skip (run twice: the second replaces the first's output)
        run_command(arguments, 600.0)  # kernels compiled and cached
        code, _, err, seconds = run_command(arguments, 600.0)
        if code != 0:
            raise SystemExit(f"the clean scene failed: {err.strip()}")
        return seconds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("corpus", type=Path, help="folder made by tools/fuzz_corpus.py")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--ratio", type=float, default=0.1)
    parser.add_argument("--timeout", type=float, default=None, help="seconds per command (default: 10x --clean)")
    parser.add_argument("--clean", type=Path, default=None, help="a valid scene whose time sets the limit")
    parser.add_argument("--jobs", type=int, default=1, help="cases run at once")
    parser.add_argument("--only", default=None, help="run only cases whose file name contains this")
    parser.add_argument("--report", type=Path, default=None, help="write every result here as JSON")
    args = parser.parse_args(argv)
    if shutil.which(sys.executable) is None:
        raise SystemExit("no Python interpreter to run nanogs_warp with")

    entries = [json.loads(line) for line in (args.corpus / "corpus.jsonl").read_text().splitlines()]
    if args.only:
        entries = [e for e in entries if args.only in e["file"]]
    if args.timeout is not None:
        timeout = args.timeout
        clean = None
    elif args.clean is not None:
        clean = clean_time(args.clean, args)
        timeout = 10.0 * clean
    else:
        raise SystemExit("give --timeout or --clean")
    print(f"{len(entries)} cases on {args.device}, limit {timeout:.1f} s per command"
          + (f" (10x the clean scene's {clean:.2f} s)" if clean else ""), flush=True)  # fmt: skip

    def run_case(entry: dict) -> CaseResult:
        path = args.corpus / entry["file"]
        result = CaseResult(entry["file"], entry["family"], entry["what"])
        result.outcomes.append(simplify_case(path, args, timeout))
        result.outcomes.append(info_case(path, timeout))
        if not result.passed:
            print(f"FAIL {result.file} ({result.what}): "
                  + "; ".join(f"{o.command}: {o.detail}" for o in result.outcomes if o.status == "FAIL"), flush=True)  # fmt: skip
        return result

    started = time.perf_counter()
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        results = list(pool.map(run_case, entries))
    elapsed = time.perf_counter() - started

    tally: dict[tuple[str, str, str], int] = {}
    for r in results:
        for o in r.outcomes:
            key = (r.family, o.command, o.status)
            tally[key] = tally.get(key, 0) + 1
    print(f"\n{len(results)} cases, {sum(r.passed for r in results)} passed, "
          f"{sum(not r.passed for r in results)} failed, {elapsed:.0f} s")  # fmt: skip
    print(f"{'family':<10} {'command':<9} {'refused':>8} {'valid':>6} {'FAIL':>5}")
    for family in sorted({r.family for r in results}):
        for command in ("simplify", "info"):
            counts = [tally.get((family, command, s), 0) for s in ("refused", "valid", "FAIL")]
            print(f"{family:<10} {command:<9} {counts[0]:>8} {counts[1]:>6} {counts[2]:>5}")
    slowest = sorted(results, key=lambda r: -r.outcomes[0].seconds)[:10]
    print("\nslowest simplify runs:")
    for r in slowest:
        o = r.outcomes[0]
        print(f"  {o.seconds:6.2f} s  {o.status:<7} {r.file} ({r.what})")
    if args.report is not None:
        report = {"device": args.device, "ratio": args.ratio, "timeout": timeout, "clean_seconds": clean,
                  "results": [{**asdict(r), "passed": r.passed} for r in results]}  # fmt: skip
        args.report.write_text(json.dumps(report, indent=1))
    return 0 if all(r.passed for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
