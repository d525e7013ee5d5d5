"""PLY read and write speed from the page cache, in GB/s of file size (median of several runs).

    python tools/io_bench.py scene.ply [--runs 7] [--out-dir DIR] [--json results.jsonl]

Read: ``load_ply`` to the CPU (header checks, parse into the splat arrays, value checks), once
plain and once hashing the file on the way (as ``batch`` does). Write: ``save_ply`` of the loaded
splats to a new file in ``--out-dir`` (default: the system's temporary directory; the previous
run's file is deleted before the clock starts). The input is read once before timing, so it comes
from the page cache; the process keeps freed memory as the commands do.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from nanogs_warp.device import init_warp, keep_freed_host_memory
from nanogs_warp.io.ply import load_ply, save_ply


def timed(fn) -> float:
    started = time.perf_counter()
    fn()
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", type=Path)
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--out-dir", type=Path, default=None, help="where the written copies go (a page-cache-backed file system)")
    parser.add_argument("--json", type=Path, default=None, help="append one JSON line with the results")
    args = parser.parse_args()

    init_warp()
    keep_freed_host_memory()
    size = args.input.stat().st_size
    with open(args.input, "rb") as f:  # into the page cache
        while f.read(16 << 20):
            pass
    splats = load_ply(args.input)
    out_dir = args.out_dir or Path(tempfile.gettempdir())
    target = out_dir / f".io_bench_{os.getpid()}.ply"

    reads, hashed_reads, writes = [], [], []
    try:
        for _ in range(args.runs):
            reads.append(timed(lambda: load_ply(args.input)))
            hashed_reads.append(timed(lambda: load_ply(args.input, digest=hashlib.sha256())))
            target.unlink(missing_ok=True)
            writes.append(timed(lambda: save_ply(splats, target)))
    finally:
        target.unlink(missing_ok=True)

    def rate(times):
        return size / statistics.median(times) / 1e9

    result = {
        "input": args.input.name,
        "bytes": size,
        "splats": splats.count,
        "runs": args.runs,
        "read_gb_s": round(rate(reads), 3),
        "read_hashed_gb_s": round(rate(hashed_reads), 3),
        "write_gb_s": round(rate(writes), 3),
        "read_s": [round(t, 4) for t in reads],
        "write_s": [round(t, 4) for t in writes],
        "cpus": os.cpu_count(),
        "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                 cwd=Path(__file__).parent).stdout.strip(),  # fmt: skip
    }
    print(f"{args.input.name}: {size / 1e6:.1f} MB, {splats.count:,} splats; read {result['read_gb_s']:.2f} GB/s "
          f"({result['read_hashed_gb_s']:.2f} GB/s hashing too), write {result['write_gb_s']:.2f} GB/s "
          f"(median of {args.runs})")  # fmt: skip
    if args.json is not None:
        with open(args.json, "a") as f:
            f.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
