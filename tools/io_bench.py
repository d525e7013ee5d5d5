"""PLY read and write speed from the page cache, in GB/s of file size (median and best of several runs).

    python tools/io_bench.py scene.ply [--runs 7] [--threads N] [--out-dir DIR] [--json results.jsonl]

Read: ``load_ply`` to the CPU (header checks, parse into the splat arrays, value checks,
quaternions normalised), once plain and once hashing the file on the way as ``batch`` does (its
piece hash, on every reader thread). Write: ``save_ply`` of the loaded splats to a new file in
``--out-dir`` (default: the system's temporary directory; the previous run's file is deleted
before the clock starts). ``--threads``: reader (and writer) threads (default: automatic, one per
8 MB of file up to the cores, at most 8). The input is read once before timing, so it comes from
the page cache; the process keeps freed memory as the commands do. Also reported: the best CPU
time of a read and of a write (every thread of the process: the work, whatever else the machine
runs), and the load average, on which the wall times of a shared machine depend.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from nanogs_warp.device import init_warp, keep_freed_host_memory
from nanogs_warp.io.ply import load_ply, save_ply
from nanogs_warp.io.ply_read import PieceHash, read_threads, set_read_threads


def timed(fn, cpu: list | None = None) -> float:
    """Wall seconds of ``fn()``; its CPU seconds (every thread of the process) go to ``cpu``."""
    started, used = time.perf_counter(), time.process_time()
    fn()
    if cpu is not None:
        cpu.append(time.process_time() - used)
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", type=Path)
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--threads", type=int, default=None, help="reader and writer threads (default: automatic)")
    parser.add_argument("--out-dir", type=Path, default=None, help="where the written copies go (a page-cache-backed file system)")
    parser.add_argument("--json", type=Path, default=None, help="append one JSON line with the results")
    args = parser.parse_args()

    init_warp()
    keep_freed_host_memory()
    set_read_threads(args.threads)
    size = args.input.stat().st_size
    with open(args.input, "rb") as f:  # into the page cache
        while f.read(16 << 20):
            pass
    splats = load_ply(args.input)
    out_dir = args.out_dir or Path(tempfile.gettempdir())
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f".io_bench_{os.getpid()}.ply"

    reads, hashed_reads, writes, read_cpu, write_cpu = [], [], [], [], []
    try:
        for _ in range(args.runs):
            reads.append(timed(lambda: load_ply(args.input), read_cpu))
            hashed_reads.append(timed(lambda: load_ply(args.input, file_hash=PieceHash(size))))
            target.unlink(missing_ok=True)
            writes.append(timed(lambda: save_ply(splats, target), write_cpu))
    finally:
        target.unlink(missing_ok=True)

    def rate(times, pick=statistics.median):
        return size / pick(times) / 1e9

    result = {
        "input": args.input.name,
        "bytes": size,
        "splats": splats.count,
        "runs": args.runs,
        "read_gb_s": round(rate(reads), 3),
        "read_hashed_gb_s": round(rate(hashed_reads), 3),
        "write_gb_s": round(rate(writes), 3),
        "read_gb_s_best": round(rate(reads, min), 3),
        "read_hashed_gb_s_best": round(rate(hashed_reads, min), 3),
        "write_gb_s_best": round(rate(writes, min), 3),
        "read_cpu_s_best": round(min(read_cpu), 4),
        "write_cpu_s_best": round(min(write_cpu), 4),
        "threads": read_threads(size),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "read_s": [round(t, 4) for t in reads],
        "read_hashed_s": [round(t, 4) for t in hashed_reads],
        "write_s": [round(t, 4) for t in writes],
        "cpus": os.cpu_count(),
        "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                 cwd=Path(__file__).parent).stdout.strip(),  # fmt: skip
    }
    print(f"{args.input.name}: {size / 1e6:.1f} MB, {splats.count:,} splats, {result['threads']} threads; GB/s median (best) "
          f"of {args.runs}: read {result['read_gb_s']:.2f} ({result['read_gb_s_best']:.2f}), hashing too "
          f"{result['read_hashed_gb_s']:.2f} ({result['read_hashed_gb_s_best']:.2f}), write {result['write_gb_s']:.2f} "
          f"({result['write_gb_s_best']:.2f}); CPU time, best: read {min(read_cpu) * 1e3:.0f} ms, write "
          f"{min(write_cpu) * 1e3:.0f} ms; load average {os.getloadavg()[0]:.2f}")  # fmt: skip
    if args.json is not None:
        with open(args.json, "a") as f:
            f.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
