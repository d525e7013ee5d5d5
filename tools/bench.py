"""Benchmark the simplification: per-stage wall times per pass, passes, throughput, memory.

    python tools/bench.py SCENES/*.ply --device cpu --ratio 0.1 --repeat 5
    python tools/bench.py playbot.ply --tile 6000000 --device cuda:0 --ratio 0.1,0.001 --json

Per scene and budget list: read time, the kernels' load as the commands load them (the package's
shipped kernels, or a compile where none ship for this machine), the first run, then --repeat
runs with state on the device: the plain wall time (median and spread) and, in separate runs, the
per-stage times with the device synchronised around each stage. Writing is timed once. JSON lines
are appended to --log (default tools/bench.jsonl) with device and commit.

SCENES is any folder of 3DGS .ply files; docs/scenes.md lists the public scenes the published
figures use and how they were converted.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).parent))

from tile_scene import tile_splats  # noqa: E402

from nanogs_warp.budgets import parse_budgets  # noqa: E402
from nanogs_warp.device import keep_freed_host_memory, resolve_device  # noqa: E402
from nanogs_warp.io.ply import load_ply, save_ply  # noqa: E402
from nanogs_warp.kernel_cache import load_kernels  # noqa: E402
from nanogs_warp.pipeline import SimplifyConfig, simplify_progressively  # noqa: E402
from nanogs_warp.timing import StageClock  # noqa: E402


def run_once(splats, targets, config, clock=None):
    """Simplifies to every target; returns (seconds, passes, counts) with the device synchronised."""
    passes = []
    wp.synchronize_device(splats.device)
    start = time.perf_counter()
    counts = []
    for _, result in simplify_progressively(splats, targets, config, on_pass=passes.append, clock=clock):
        counts.append(result.count)
    wp.synchronize_device(splats.device)
    return time.perf_counter() - start, len(passes), counts, result


def spread(values):
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def bench_scene(path: Path, args, device) -> dict:
    t = time.perf_counter()
    host = load_ply(path)
    read_s = time.perf_counter() - t
    name = path.stem
    if args.tile:
        host = tile_splats(host, args.tile, device="cpu")
        name = f"{path.stem}x{args.tile}"
    input_bytes = host.count * (3 + 4 + 3 + 1 + host.features.shape[1] + host.extras.shape[1]) * 4
    budgets = parse_budgets(args.ratio, None)
    targets = sorted({b.target(host.count) for b in budgets}, reverse=True)
    given = {"k": args.k, "samples": args.samples, "cost": args.cost, "operator": args.operator,
             "prune_opacity": args.prune_opacity, "pass_fraction": args.pass_fraction}  # fmt: skip
    config = SimplifyConfig.preset(args.preset, **{name: value for name, value in given.items() if value is not None})

    t = time.perf_counter()
    splats = host.to(device)
    wp.synchronize_device(device)
    upload_s = time.perf_counter() - t
    kernels_s = load_kernels(device)  # the merge's modules, as the commands load them: no compile where they ship
    first_s, passes, counts, _ = run_once(splats, targets, config)
    plain = [run_once(splats, targets, config)[0] for _ in range(args.repeat)]
    clocks = []
    for _ in range(args.repeat):
        clock = StageClock(device)
        run_once(splats, targets, config, clock)
        clocks.append(clock)
    stages = {name: spread([c.totals().get(name, 0.0) for c in clocks]) for name in clocks[0].totals()}
    per_pass = [dict(times) for times in clocks[len(clocks) // 2].passes]

    _, _, _, result = run_once(splats, targets[-1:], config)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        save_ply(result, Path(tmp) / "out.ply")
        write_s = time.perf_counter() - t
    record = {
        "scene": name,
        "input_count": host.count,
        "device": str(device),
        "device_name": device.name,
        "ratios": args.ratio,
        "counts": counts,
        "passes": passes,
        "read_s": read_s,
        "upload_s": upload_s,
        "kernels_s": kernels_s,
        "first_run_s": first_s,
        "run_s": spread(plain),
        "stages_s": stages,
        "per_pass_s": per_pass,
        "write_smallest_s": write_s,
        "splats_per_s": host.count / statistics.median(plain),
        "peak_host_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "input_mb_float32": input_bytes / 2**20,
    }
    if device.is_cuda:
        record["peak_device_mb"] = wp.get_mempool_used_mem_high(device) / 2**20
    return record


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+", type=Path, help="3DGS .ply files to benchmark")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--ratio", default="0.1")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--tile", type=int, default=0, help="tile each scene to this many splats first")
    parser.add_argument("--preset", default="default", help="default, fast or paper; the options below override it")
    parser.add_argument("--k", type=int, default=None, help="default: the preset's (by scene size, as the commands)")
    parser.add_argument("--samples", type=int, default=None)
    parser.add_argument("--cost", default=None)
    parser.add_argument("--operator", default=None)
    parser.add_argument("--prune-opacity", type=float, default=None)
    parser.add_argument("--pass-fraction", type=float, default=None)
    parser.add_argument("--json", action="store_true", help="print the records as JSON")
    parser.add_argument("--log", type=Path, default=Path(__file__).parent / "bench.jsonl")
    args = parser.parse_args()
    device = resolve_device(args.device)
    keep_freed_host_memory()  # as the commands do
    records = []
    for path in args.scenes:
        record = bench_scene(path, args, device)
        record["commit"] = commit()
        records.append(record)
        with open(args.log, "a") as log:
            log.write(json.dumps(record) + "\n")
        if not args.json:
            stages = " ".join(f"{k}={v['median'] * 1e3:.0f}" for k, v in record["stages_s"].items())
            print(
                f"{record['scene']:>22} {record['input_count']:>10,} {record['device']:>7} ratios={args.ratio} "
                f"passes={record['passes']:>2} run={record['run_s']['median']:.3f}s "
                f"(kernels {record['kernels_s']:.2f}s, first {record['first_run_s']:.2f}s) read={record['read_s']:.3f}s "
                f"write={record['write_smallest_s']:.3f}s ms: {stages}",
                flush=True,
            )
    if args.json:
        print(json.dumps(records, indent=2))


if __name__ == "__main__":
    main()
