"""End-to-end A/B of ``nanogs-warp simplify``: versions of the package run alternately, each in a
fresh process, wall time by ``/usr/bin/time`` (process start to exit) and the command's own
``--json`` stage clock; the outputs' SHA-256 of each version's first run are printed so that a
change can be checked byte for byte.

    python tools/simplify_ab.py /dev/shm/t6.ply --runs 10 base=../base new=.
    python tools/simplify_ab.py t6.ply --runs 6 new=. eager=.:CUDA_MODULE_LOADING=EAGER

Each version is NAME=DIR[:VAR=VALUE,...]: DIR (a checkout of this repository, with the kernels
importable as ``nanogs_warp.kernels``: an installed copy or a link ``nanogs_warp/kernels`` ->
``../kernels``) goes first on PYTHONPATH, after ``--path`` (Warp's folder, if it is not installed),
and the variables are set for that version alone. Run each version once before (the kernel cache
must be warm) and keep the input in memory (/dev/shm). JSON lines go to --log.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def parse_version(text: str) -> tuple[str, Path, dict[str, str]]:
    name, sep, rest = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=DIR[:VAR=VALUE,...]")
    folder, _, variables = rest.partition(":")
    env = {}
    for item in filter(None, variables.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"{item!r}: expected VAR=VALUE")
        env[key] = value
    return name, Path(folder).resolve(), env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input")
    parser.add_argument("versions", nargs="+", type=parse_version, metavar="NAME=DIR[:VAR=VALUE,...]")
    parser.add_argument("--runs", type=int, default=6)
    parser.add_argument("--ratio", default="0.1,0.01,0.001")
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--output", default=None, help="output path (default: o.ply in a temporary folder)")
    parser.add_argument("--path", default="", help="folders put on PYTHONPATH after each version's (os.pathsep between)")
    parser.add_argument("--log", default=None, help="JSON lines, one per run")
    args = parser.parse_args()
    timer = shutil.which("time") if not Path("/usr/bin/time").exists() else "/usr/bin/time"
    if timer is None:
        sys.exit("simplify_ab: needs /usr/bin/time (GNU time)")
    work = Path(tempfile.mkdtemp(prefix="simplify_ab_"))
    output = Path(args.output) if args.output else work / "o.ply"
    budgets = args.ratio.split(",")
    outputs = [output] if len(budgets) == 1 else [output.with_name(f"{output.stem}_{b}{output.suffix}") for b in budgets]
    command = [sys.executable, "-m", "nanogs_warp", "simplify", str(Path(args.input).resolve()), "-o", str(output),
               "--ratio", args.ratio, "--device", args.device, "-w", "--json"]  # fmt: skip
    log = open(args.log, "a") if args.log else None
    results: dict[str, list[tuple[float, dict]]] = {name: [] for name, _, _ in args.versions}
    shas: dict[str, str] = {}
    for run in range(args.runs):
        for name, folder, variables in args.versions:
            path = os.pathsep.join(p for p in (str(folder), args.path) if p)
            env = dict(os.environ, PYTHONPATH=path, **variables)
            wall_file = work / "wall"
            done = subprocess.run([timer, "-f", "%e", "-o", str(wall_file), *command], cwd=folder, env=env,
                                  capture_output=True, text=True)  # fmt: skip
            if done.returncode != 0:
                sys.exit(f"{name}: exit code {done.returncode}\n{done.stderr[-3000:]}")
            wall = float(wall_file.read_text().split()[-1])
            summary = json.loads(done.stdout)
            stages = dict(summary["seconds"]["stages"], total=summary["seconds"]["total"])
            if run == 0:
                shas[name] = " ".join(hashlib.sha256(p.read_bytes()).hexdigest()[:16] for p in outputs)
            results[name].append((wall, stages))
            if log:
                log.write(json.dumps({"version": name, "run": run, "wall": wall, "stages": stages}) + "\n")
                log.flush()
    print(f"{'version':12s} {'median':>7s} {'mean':>6s} {'min':>6s} {'max':>6s}  stage medians (s)")
    for name, runs in results.items():
        walls = [w for w, _ in runs]
        keys = list(dict.fromkeys(k for _, s in runs for k in s))
        medians = {k: round(statistics.median(s.get(k, 0.0) for _, s in runs), 3) for k in keys}
        print(f"{name:12s} {statistics.median(walls):7.2f} {statistics.mean(walls):6.2f} {min(walls):6.2f} {max(walls):6.2f}  {medians}")
        print(f"{'':12s} outputs {shas[name]}")
    same = len(set(shas.values())) == 1
    print("outputs byte-identical across versions" if same else "OUTPUTS DIFFER between versions")
    shutil.rmtree(work, ignore_errors=True)
    if not same:
        sys.exit(1)


if __name__ == "__main__":
    main()
