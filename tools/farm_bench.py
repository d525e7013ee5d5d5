"""Render-farm throughput of ``nanogs-warp batch``: N tiled scenes of a given size, to several budgets.

    python tools/farm_bench.py SOURCE.ply --scenes 8 --splats 6000000 --workdir /tmp/farm
    python tools/farm_bench.py SOURCE.ply --scenes 24 --splats 6000000 --workdir /tmp/farm --runs cuda:0 "cuda:0 --mps"
    python tools/farm_bench.py SOURCE.ply --scenes 4 --splats 200000 --runs cpu      # on a CPU machine

Makes ``--scenes`` copies of SOURCE tiled to ``--splats`` splats (each a few splats apart, so none is
the same file) in WORKDIR/scenes, reads them once into the page cache, then runs ``batch --force``
over them once per entry of ``--runs`` (``--devices`` values; default: ``cuda:0`` and, with several
GPUs, ``all``; ``cpu`` without a GPU). For each run it reports the wall time, the steady-state rate
(scenes finished per second once every worker has finished its first scene, per device:
``steady_rate``), the median read / upload / simplify / download / write seconds of a scene from the
batch's JSON, the device stages' share of the wall time (upload + simplify + download summed over
the scenes of a device, divided by the wall time: how busy the pipeline kept the device) and, when
``nvidia-smi`` is there, each GPU's busy fraction (samples every 100 ms with utilisation above 0)
and mean utilisation. The last line gives the scaling of the last run over the first. ``--simplify``
also times ``nanogs-warp simplify`` of the first scene end to end (a fresh process each time, median
of 3) and prints where its time went (``seconds.stages`` of its JSON, of the fastest run).
Results are appended as JSON lines to ``--json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from tile_scene import tile_arrays  # noqa: E402

from nanogs_warp.io.ply import load_ply, save_ply  # noqa: E402
from nanogs_warp.splats import SplatSet  # noqa: E402


def make_scenes(source: Path, count: int, splats: int, folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / f"tiled_{splats}_{i}.ply" for i in range(count)]
    if all(p.exists() for p in paths):
        return paths
    base = load_ply(source)
    arrays = base.to_numpy()
    for i, path in enumerate(paths):
        if not path.exists():
            tiled = tile_arrays(arrays, splats + i)
            save_ply(SplatSet.from_numpy(**tiled, layout=base.layout, device="cpu"), path)
    return paths


def into_page_cache(paths: list[Path]) -> None:
    for path in paths:
        with open(path, "rb") as f:
            while f.read(64 << 20):
                pass


class GpuSampler:
    """nvidia-smi utilisation every 100 ms, per GPU index, while running."""

    def __init__(self):
        self.samples: dict[str, list[int]] = {}
        self.process = None
        if shutil.which("nvidia-smi"):
            self.process = subprocess.Popen(
                ["nvidia-smi", "--query-gpu=index,utilization.gpu", "--format=csv,noheader,nounits", "-lms", "100"],
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)  # fmt: skip
            self.thread = threading.Thread(target=self._read, daemon=True)
            self.thread.start()

    def _read(self):
        for line in self.process.stdout:
            parts = [p.strip() for p in line.split(",")]
            if len(parts) == 2 and parts[1].isdigit():
                self.samples.setdefault(parts[0], []).append(int(parts[1]))

    def stop(self) -> dict[str, dict[str, float]]:
        if self.process is None:
            return {}
        self.process.terminate()
        self.process.wait()
        self.thread.join(2)
        return {gpu: {"busy_fraction": round(sum(u > 0 for u in s) / len(s), 3), "mean_utilisation": round(statistics.mean(s), 1),
                      "samples": len(s)} for gpu, s in sorted(self.samples.items()) if s}  # fmt: skip


def steady_rate(finished_at: list[float], workers: int) -> float | None:
    """Scenes finished per second once the pipeline is full: from the ``workers``-th finish (every
    worker has finished its first scene) to the last, (N - W) / (t_N - t_W); None with no scene
    after that. Counting from the first finish instead would credit the scenes that several
    workers started together to a rate they were not finished at (twelve scenes on six workers
    read twice the run's rate)."""
    full = max(1, workers)
    if len(finished_at) <= full or finished_at[-1] <= finished_at[full - 1]:
        return None
    return (len(finished_at) - full) / (finished_at[-1] - finished_at[full - 1])


def run_batch(scenes_dir: Path, out_dir: Path, ratios: str, devices: str, extra: list[str]) -> dict:
    command = [sys.executable, "-m", "nanogs_warp", "batch", str(scenes_dir), "-o", str(out_dir), "--ratio", ratios,
               "--devices", devices, "--force", "--json", *extra]  # fmt: skip
    sampler = GpuSampler()
    started = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
    finished_at = []
    started_first = 0  # scenes started before any finished: one per worker
    stdout_parts = []
    reader = threading.Thread(target=lambda: stdout_parts.append(process.stdout.read()), daemon=True)
    reader.start()
    for line in process.stderr:
        if " splats in " in line or "FAILED" in line or "skipped" in line:
            finished_at.append(time.monotonic() - started)
        elif "started on" in line:
            if not finished_at:
                started_first += 1
        elif line.strip():
            sys.stderr.write(line)
    process.wait()
    reader.join()
    wall = time.monotonic() - started
    gpus = sampler.stop()
    if process.returncode not in (0, 1):
        raise SystemExit(f"farm_bench: batch failed (exit {process.returncode})")
    summary = json.loads("".join(stdout_parts))
    scenes = summary["scenes"]
    devices_used = sorted({s["device"] for s in scenes})
    steady = steady_rate(finished_at, started_first)

    def median_stage(name):
        values = [s["stages"][name] for s in scenes if name in s.get("stages", {})]
        return round(statistics.median(values), 4) if values else None

    device_s = {d: sum(s.get("stages", {}).get(k, 0.0) for s in scenes if s["device"] == d for k in ("upload", "simplify", "download"))
                for d in devices_used}  # fmt: skip
    return {
        "devices": devices,
        "devices_used": devices_used,
        "device_stage_fraction": {d: round(v / wall, 3) for d, v in device_s.items()},
        "scenes": len(scenes),
        "failed": summary["failed"],
        "wall_s": round(wall, 3),
        "scenes_per_s": round(len(scenes) / wall, 3),
        "steady_scenes_per_s": round(steady, 3) if steady else None,
        "steady_scenes_per_s_per_device": round(steady / len(devices_used), 3) if steady else None,
        "read_s": median_stage("read"),
        "upload_s": median_stage("upload"),
        "simplify_s": median_stage("simplify"),
        "download_s": median_stage("download"),
        "write_s": median_stage("write"),
        "scene_s": round(statistics.median(s["seconds"] for s in scenes), 4),
        "gpus": gpus,
    }


def time_simplify(scene: Path, out_dir: Path, ratios: str, device: str) -> dict:
    walls, reported, stages = [], [], []
    for _ in range(3):
        started = time.monotonic()
        result = subprocess.run([sys.executable, "-m", "nanogs_warp", "simplify", str(scene), "-o", str(out_dir / "single.ply"),
                                 "--ratio", ratios, "--device", device, "--json", "-w"], capture_output=True, text=True)  # fmt: skip
        walls.append(time.monotonic() - started)
        if result.returncode != 0:
            raise SystemExit(f"farm_bench: simplify failed: {result.stderr.strip()}")
        reported.append(json.loads(result.stdout)["seconds"])
    best = min(range(3), key=lambda i: walls[i])
    return {"device": device, "wall_s_median": round(statistics.median(walls), 3), "wall_s": [round(w, 3) for w in walls],
            "read_s": reported[best]["read"], "total_s": reported[best]["total"],
            "stages": reported[best].get("stages", {})}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path, help="a real scene to tile")
    parser.add_argument("--scenes", type=int, default=8)
    parser.add_argument("--splats", type=int, default=6_000_000)
    parser.add_argument("--ratio", default="0.1,0.01,0.001")
    parser.add_argument("--runs", nargs="+", default=None,
                        help="one batch run each: a --devices value and any more batch options, e.g. cuda:0 all 'cpu --workers 2'")
    parser.add_argument("--workdir", type=Path, required=True, help="scenes and outputs go here (keep it on a fast disk)")
    parser.add_argument("--simplify", action="store_true", help="also time `nanogs-warp simplify` of one scene end to end")
    parser.add_argument("--json", type=Path, default=None, help="append the results as one JSON line")
    args = parser.parse_args()

    gpus = 0
    if shutil.which("nvidia-smi"):
        listing = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout
        gpus = sum(line.startswith("GPU ") for line in listing.splitlines())
    runs = args.runs or (["cuda:0", "all"] if gpus > 1 else ["cuda:0"] if gpus == 1 else ["cpu"])

    scenes = make_scenes(args.source, args.scenes, args.splats, args.workdir / "scenes")
    into_page_cache(scenes)
    size_mb = sum(p.stat().st_size for p in scenes) / len(scenes) / 1e6
    warm = "cuda" if gpus else "cpu"  # kernels compiled before any clock starts
    subprocess.run([sys.executable, "-m", "nanogs_warp", "warmup", "-q", "--arch", "none", "--device", warm], check=True)

    results = []
    for k, run in enumerate(runs):
        devices, *extra = shlex.split(run)
        results.append(run_batch(args.workdir / "scenes", args.workdir / f"out_{k}", args.ratio, devices, extra))
        results[-1]["run"] = run
    single = time_simplify(scenes[0], args.workdir, args.ratio, "cuda:0" if gpus else "cpu") if args.simplify else None

    print(f"{len(scenes)} scenes of {args.splats:,} splats ({size_mb:.0f} MB each), budgets {args.ratio}")
    print(f"{'run':>18} {'devices':>8} {'wall s':>8} {'scenes/s':>9} {'steady/s/dev':>13} {'read s':>7} {'upload s':>8} "
          f"{'simplify s':>10} {'download s':>10} {'write s':>8} {'device stages':>13}  GPU busy")  # fmt: skip
    for r in results:
        busy = ", ".join(f"{g}: {v['busy_fraction']:.0%} ({v['mean_utilisation']:.0f}%)" for g, v in r["gpus"].items()) or "-"
        steady = f"{r['steady_scenes_per_s_per_device']:.3f}" if r["steady_scenes_per_s_per_device"] else "-"
        share = "/".join(f"{v:.0%}" for v in r["device_stage_fraction"].values())

        def cell(key, width):
            return f"{r[key]:>{width}.3f}" if r[key] is not None else f"{'-':>{width}}"

        print(f"{r['run']:>18} {len(r['devices_used']):>8} {r['wall_s']:>8.2f} {r['scenes_per_s']:>9.3f} {steady:>13} "
              f"{cell('read_s', 7)} {cell('upload_s', 8)} {cell('simplify_s', 10)} {cell('download_s', 10)} {cell('write_s', 8)} "
              f"{share:>13}  {busy}")  # fmt: skip
        if r["failed"]:
            print(f"  {r['failed']} scene(s) failed")
    if len(results) > 1 and results[0]["steady_scenes_per_s"] and results[-1]["steady_scenes_per_s"]:
        print(f"scaling {runs[0]} -> {runs[-1]}: {results[-1]['steady_scenes_per_s'] / results[0]['steady_scenes_per_s']:.2f}x "
              f"steady state, {results[0]['wall_s'] / results[-1]['wall_s']:.2f}x wall")  # fmt: skip
    if single:
        print(f"simplify {scenes[0].name} on {single['device']}: {single['wall_s_median']:.2f} s wall (median of 3; "
              f"read {single['read_s']:.2f} s, total in-process {single['total_s']:.2f} s)")  # fmt: skip
        if single["stages"]:
            print("  stages of the fastest run (s): " + ", ".join(f"{k} {v:.3f}" for k, v in single["stages"].items()))
    if args.json is not None:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent).stdout.strip()  # fmt: skip
        record = {"splats": args.splats, "scenes": len(scenes), "mb_per_scene": round(size_mb, 1), "ratio": args.ratio,
                  "runs": results, "simplify": single, "commit": commit, "gpus": gpus}  # fmt: skip
        with open(args.json, "a") as f:
            f.write(json.dumps(record) + "\n")


if __name__ == "__main__":
    main()
