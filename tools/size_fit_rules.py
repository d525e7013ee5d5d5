"""How the size fit's rule for a factor's gain would fare on eval's orbit and on unseen cameras.

The size fit (``nanogs_warp/refinement/size_fit.py``) scores a factor by its PSNR gain in two view
sets of its own, coarse (256 x 256) and fine (the same cameras zoomed 4x), and takes the smaller
of the two. This measures that choice against others: for each scene, each fitted budget (at most
1 % of the input) and each factor STEP^k, |k| <= MOST_STEPS, it records the fit's two gains for
the unfitted output and the output's PSNR on ``eval``'s orbit and on ``tools/unseen_cameras.py``'s
three sets (close-ups, the orbit at 512 x 512, a tight orbit). Each rule below is then replayed
through the fit's own search (``size_fit.best_step``: outward from factor 1 while the gain rises,
the best positive gain):

- ``min``: the smaller of the two gains (the fit's rule);
- ``mean``: their mean; ``coarse-2:1``: two parts coarse, one part fine;
- ``coarse`` or ``fine``: one set alone.

It prints, per rule and camera set, the mean and the worst change over the unfitted outputs, every
cell's chosen step, and leave-one-scene-out choices among the rules (by the mean plus the worst
cell, on the orbit alone and on all four sets).

    python tools/size_fit_rules.py SCENES/*.ply -o fit_rules.jsonl       # about 20 min on 2 cores, 12 scenes
    python tools/size_fit_rules.py --table fit_rules.jsonl               # the tables again, no rendering
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import statistics
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from unseen_cameras import camera_sets  # noqa: E402  (this folder's)

from nanogs_warp.config import SimplifyConfig  # noqa: E402
from nanogs_warp.device import init_warp, resolve_device  # noqa: E402
from nanogs_warp.kernel_cache import ALL_MODULES, load_kernels  # noqa: E402
from nanogs_warp.eval.cameras import orbit_cameras  # noqa: E402
from nanogs_warp.eval.evaluate import evaluate  # noqa: E402
from nanogs_warp.io.ply import load_ply  # noqa: E402
from nanogs_warp.pipeline import simplify_progressively  # noqa: E402
from nanogs_warp.refinement import size_fit  # noqa: E402

RATIOS = ("0.1", "0.01", "0.001")
CAMERA_SETS = ("orbit", "closeup", "orbit512", "tight")
RULES = {
    "min": lambda coarse, fine: min(coarse, fine),
    "mean": lambda coarse, fine: 0.5 * (coarse + fine),
    "coarse-2:1": lambda coarse, fine: (2.0 * coarse + fine) / 3.0,
    "coarse": lambda coarse, fine: coarse,
    "fine": lambda coarse, fine: fine,
}


def measure(paths: list[Path], out_path: Path, device) -> None:
    """Appends one JSON line per (scene, fitted budget, step k) to ``out_path``."""
    steps = range(-size_fit.MOST_STEPS, size_fit.MOST_STEPS + 1)
    config = replace(SimplifyConfig(), fit_size=False)
    with open(out_path, "a") as out:
        for path in paths:
            splats = load_ply(path, device=device)
            targets = [math.ceil(float(r) * splats.count) for r in RATIOS]
            fit = size_fit.SizeFit(splats, config.seed)
            sets = {"orbit": orbit_cameras(splats), **camera_sets(splats)}
            for target, output in simplify_progressively(splats, targets, config):
                gains = fit.view_gains(output, [size_fit.STEP**k for k in steps]) if fit.applies(output.count) else None
                if gains is None:
                    continue
                resized = [size_fit.resized(output, size_fit.STEP**k) for k in steps]
                psnr = {name: [t["psnr"]["mean"] for t in evaluate(splats, resized, cameras, device)["tests"]]
                        for name, cameras in sets.items()}  # fmt: skip
                for n, k in enumerate(steps):
                    row = {"scene": path.stem, "ratio": RATIOS[targets.index(target)], "count": output.count, "k": k,
                           "coarse": gains[n][0], "fine": gains[n][1], **{name: psnr[name][n] for name in CAMERA_SETS}}  # fmt: skip
                    out.write(json.dumps(row) + "\n")
                out.flush()
            print(f"{path.stem}: done", flush=True)


def chosen_step(cell: dict[int, dict], gain) -> int:
    """The step the fit's own search (``size_fit.best_step``) takes with ``gain(coarse, fine)``."""
    return size_fit.best_step(lambda k, floor: gain(cell[k]["coarse"], cell[k]["fine"]))


def changes(cells: dict, keys: list, rule: str) -> dict[str, list[float]]:
    """Per camera set, the PSNR change of each cell's chosen step over its unfitted output."""
    result = {name: [] for name in CAMERA_SETS}
    for key in keys:
        cell = cells[key]
        k = chosen_step(cell, RULES[rule])
        for name in CAMERA_SETS:
            result[name].append(cell[k][name] - cell[0][name])
    return result


def report(rows: list[dict]) -> None:
    cells: dict[tuple[str, str], dict[int, dict]] = collections.defaultdict(dict)
    for row in rows:
        cells[(row["scene"], row["ratio"])][row["k"]] = row
    keys = sorted(cells)
    print(f"{len(keys)} fitted outputs; PSNR change over the unfitted output (dB), mean / worst cell")
    print(f"{'rule':11s}" + "".join(f"{name:>18s}" for name in CAMERA_SETS))
    for rule in RULES:
        per = changes(cells, keys, rule)
        print(f"{rule:11s}" + "".join(f"{statistics.mean(per[n]):+9.3f} / {min(per[n]):+5.2f}" for n in CAMERA_SETS))
    print("\nchosen step k (factor STEP^k) and orbit PSNR per rule:")
    for key in keys:
        cell = cells[key]
        picks = {rule: chosen_step(cell, RULES[rule]) for rule in RULES}
        print(f"  {key[0]:20s} {key[1]:6s} " + "  ".join(f"{rule} {k:+d} ({cell[k]['orbit']:.2f})" for rule, k in picks.items()))
    scenes = sorted({key[0] for key in keys})
    for sets, label in ((("orbit",), "the orbit alone"), (CAMERA_SETS, "all four sets")):
        picks, held = [], {name: [] for name in CAMERA_SETS}
        for scene in scenes:
            train = [key for key in keys if key[0] != scene]

            def score(rule: str) -> float:
                per = changes(cells, train, rule)
                return sum(statistics.mean(per[n]) + min(per[n]) for n in sets)

            best = max(RULES, key=score)
            picks.append(best)
            for name, values in changes(cells, [key for key in keys if key[0] == scene], best).items():
                held[name] += values
        print(f"\nleave-one-scene-out by {label}: picks {dict(collections.Counter(picks))}; held out, mean / worst: "
              + ", ".join(f"{n} {statistics.mean(v):+.3f} / {min(v):+.2f}" for n, v in held.items()))  # fmt: skip


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="*", type=Path, help="unsimplified scenes (.ply)")
    parser.add_argument("-o", "--out", type=Path, help="JSON lines to append the measurements to")
    parser.add_argument("--table", type=Path, help="print the tables of a measurements file instead of measuring")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    if args.table is not None:
        report([json.loads(line) for line in open(args.table)])
        return 0
    if not args.scenes or args.out is None:
        parser.error("give scenes and -o, or --table")
    init_warp()
    device = resolve_device(args.device)
    load_kernels(device, ALL_MODULES)  # as the commands load them: no compile where they ship
    measure(args.scenes, args.out, device)
    report([json.loads(line) for line in open(args.out)])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
