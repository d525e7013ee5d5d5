"""Quality sweep: every scene in a folder x budgets x configurations, evaluated against the original.

    python tools/quality_sweep.py SCENES/ -o sweep/ --device cpu
    python tools/quality_sweep.py SCENES/ -o sweep/ --configs paper,area --scenes guitar
    python tools/quality_sweep.py -o sweep/ --table-only          # rebuild the markdown from the JSON lines

Per scene: the reference is loaded once, its orbit cameras (16 views, 256 x 256 by default, black
background) and images are made once; each NanoGS configuration runs one progressive
simplification that yields every budget, each baseline keeps a subset per budget; every result is
rendered and compared in-process (kernels compile once). Results are appended to
``OUT/sweep.jsonl`` (one line per scene x budget x configuration; a (scene, configuration) whose
lines are there with the same definition is skipped, so an interrupted sweep resumes) and
``OUT/sweep.md`` is rewritten from all lines: mean PSNR per configuration and budget, PSNR per scene,
and the full table (PSNR, SSIM, FG-PSNR, colour shift, seconds).

``seconds`` of a NanoGS row is the wall time of its progressive run from the start until that budget
was reached (so the 0.001 row is the whole run); of a baseline row, the time to select its subset.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).parent))

from baselines import baseline  # noqa: E402

import nanogs_warp.config as config_module  # noqa: E402
from nanogs_warp.cost import COSTS  # noqa: E402
from nanogs_warp.device import resolve_device  # noqa: E402
from nanogs_warp.kernel_cache import ALL_MODULES, load_kernels  # noqa: E402
from nanogs_warp.eval.cameras import orbit_cameras  # noqa: E402
from nanogs_warp.eval.evaluate import compare_images, render_all  # noqa: E402
from nanogs_warp.io.ply import load_ply, save_ply  # noqa: E402
from nanogs_warp.pipeline import SimplifyConfig, target_count  # noqa: E402
from nanogs_warp.refinement.simplify import simplify_progressively  # noqa: E402 - with the size fit, as the command line

RATIOS = (0.1, 0.01, 0.001)
PAPER = dataclasses.asdict(SimplifyConfig.paper())  # every setting, so --define can change any of them


def _setting(default, value: str, parser, definition: str):
    """``value`` as the type of the paper's ``default`` for that key; booleans from 0 / 1 / true /
    false (``bool("0")`` would be True)."""
    if isinstance(default, bool):
        if value.lower() not in ("0", "1", "true", "false"):
            parser.error(f"--define {definition!r}: {value!r} is not 0, 1, true or false")
        return value.lower() in ("1", "true")
    return type(default)(value)


def nanogs(**changes) -> dict:
    """A NanoGS configuration: the paper's settings with ``changes``."""
    return {"kind": "nanogs", **PAPER, **changes}


# The default (docs/quality.md): coverage operator, field cost, no opacity pruning, k by scene size
# (None: 24 below 65,536 splats, else 16), at most 45 % of the splats merged a pass, none above 3x
# the pass's median pair cost: SimplifyConfig's defaults.
RECOMMENDED = dataclasses.asdict(SimplifyConfig())
# An earlier default, now --preset fast: the Runnalls cost and whole matchings.
RUNNALLS_DEFAULT = dataclasses.asdict(SimplifyConfig.preset("fast"))

# name -> definition. "paper" is the paper's configuration (SimplifyConfig's defaults when this was written).
CONFIGS: dict[str, dict] = {
    "paper": nanogs(),
    # one change from the paper
    "area": nanogs(operator="area"),
    "coverage": nanogs(operator="coverage"),
    "mse": nanogs(cost="mse"),
    "runnalls": nanogs(cost="runnalls"),
    "s8": nanogs(samples=8),
    "app0.25": nanogs(lambda_app=0.25),
    "app4": nanogs(lambda_app=4.0),
    "prune0": nanogs(prune_opacity=0.0),
    "k24": nanogs(k=24),
    # combinations
    "area+runnalls": nanogs(operator="area", cost="runnalls"),
    "area+runnalls+prune0": nanogs(operator="area", cost="runnalls", prune_opacity=0.0),
    "coverage+runnalls": nanogs(operator="coverage", cost="runnalls"),
    "coverage+runnalls+prune0": nanogs(operator="coverage", cost="runnalls", prune_opacity=0.0),
    "default": nanogs(**RECOMMENDED),
    "runnalls-default": nanogs(**RUNNALLS_DEFAULT),
    "default-f0.25": nanogs(**{**RECOMMENDED, "pass_fraction": 0.25}),
    "default-f0.5": nanogs(**{**RECOMMENDED, "pass_fraction": 0.5}),
    # the recommended configuration with one change back, or one neighbour
    "rec-prune0.1": nanogs(**{**RECOMMENDED, "prune_opacity": 0.1}),
    "rec-k16": nanogs(**{**RECOMMENDED, "k": 16}),
    "rec-k20": nanogs(**{**RECOMMENDED, "k": 20}),
    "rec-k24": nanogs(**{**RECOMMENDED, "k": 24}),
    "rec-area": nanogs(**{**RECOMMENDED, "operator": "area"}),
    "rec-mpmm": nanogs(**{**RECOMMENDED, "operator": "mpmm"}),
    "rec-idiv": nanogs(**{**RECOMMENDED, "cost": "idiv"}),
    "rec-app0.5": nanogs(**{**RECOMMENDED, "lambda_app": 0.5}),
    "rec-app2": nanogs(**{**RECOMMENDED, "lambda_app": 2.0}),
    # baselines
    "topk": {"kind": "baseline", "method": "topk", "seed": 0},
    "random": {"kind": "baseline", "method": "random", "seed": 0},
}
DEFAULT_CONFIGS = list(CONFIGS)


def _with_params(base, params, lambda_geo, lambda_app, samples, seed):
    return dataclasses.replace(base(lambda_geo, lambda_app, samples, seed), **params)


def commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent)
        return out.stdout.strip() or None
    except OSError:
        return None


def _row(scene: str, config: str, spec: dict, ratio: float, result, test_images, ref_images, view_names, seconds: float) -> dict:
    m = compare_images(ref_images, test_images, view_names)
    return {
        "scene": scene,
        "config": config,
        "spec": spec,
        "ratio": ratio,
        "count": result.count,
        "psnr": m["psnr"]["mean"],
        "ssim": m["ssim"]["mean"],
        "fg_psnr": m["fg_psnr"]["mean"],
        "colour_shift": m["colour_shift"]["mean"],
        "psnr_worst": m["psnr"]["worst"],
        "seconds": round(seconds, 4),
    }


def run_config(scene, splats, config, spec, ratios, cameras, ref_images, view_names, device, keep_dir=None):
    """Rows of one configuration at every budget on one scene."""
    targets = {ratio: target_count(splats.count, ratio) for ratio in ratios}
    rows = []
    if spec["kind"] == "baseline":
        for ratio, target in targets.items():
            started = time.perf_counter()
            result = baseline(splats, spec["method"], target, spec["seed"])
            seconds = time.perf_counter() - started
            rows.append(_row(scene, config, spec, ratio, result, render_all(result, cameras), ref_images, view_names, seconds))
            if keep_dir is not None:
                save_ply(result, keep_dir / f"{scene}_{config}_{ratio:g}.ply")
        return rows
    cfg = SimplifyConfig(**{k: v for k, v in spec.items() if k != "kind"})
    ratio_of = {}
    for ratio, target in targets.items():
        ratio_of.setdefault(target, []).append(ratio)
    wp.synchronize_device(device)
    started = time.perf_counter()
    paused = 0.0
    for target, result in simplify_progressively(splats, list(ratio_of), cfg):
        wp.synchronize_device(device)
        reached = time.perf_counter() - started - paused
        pause_start = time.perf_counter()
        images = render_all(result, cameras)
        for ratio in ratio_of[target]:
            rows.append(_row(scene, config, spec, ratio, result, images, ref_images, view_names, reached))
            if keep_dir is not None:
                save_ply(result, keep_dir / f"{scene}_{config}_{ratio:g}.ply")
        paused += time.perf_counter() - pause_start
    return rows


def load_rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _f(value, digits=2):
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def markdown(rows: list[dict], moonshot: dict | None = None) -> str:
    """Summary (mean PSNR per config and budget), PSNR per scene, and the full table."""
    latest = {}
    for r in rows:  # the last line of a (scene, config, ratio) wins
        latest[(r["scene"], r["config"], r["ratio"])] = r
    rows = list(latest.values())
    scenes = sorted({r["scene"] for r in rows})
    configs = list(dict.fromkeys(r["config"] for r in rows))
    ratios = sorted({r["ratio"] for r in rows}, reverse=True)
    get = {(r["scene"], r["config"], r["ratio"]): r for r in rows}
    out = ["## Mean PSNR (dB) over scenes, per configuration and budget", ""]
    complete = [c for c in configs if all((s, c, q) in get for s in scenes for q in ratios)]
    out.append("| config | " + " | ".join(f"ρ={q:g}" for q in ratios) + " | mean | SSIM mean | seconds (all budgets, sum over scenes) |")
    out.append("|---|" + "---:|" * (len(ratios) + 3))
    for c in complete:
        means = [float(np.mean([get[(s, c, q)]["psnr"] for s in scenes])) for q in ratios]
        ssim = float(np.mean([get[(s, c, q)]["ssim"] for s in scenes for q in ratios]))
        secs = sum(max(get[(s, c, q)]["seconds"] for q in ratios) if get[(s, c, ratios[0])]["spec"]["kind"] == "nanogs"
                   else sum(get[(s, c, q)]["seconds"] for q in ratios) for s in scenes)  # fmt: skip
        out.append(f"| {c} | " + " | ".join(_f(m) for m in means) + f" | {_f(float(np.mean(means)))} | {_f(ssim, 4)} | {_f(secs, 1)} |")
    if len(complete) < len(configs):
        out.append("")
        out.append("Configurations not run on every scene and budget (left out above): " + ", ".join(c for c in configs if c not in complete))
    headline = [c for c in ("recommended", "paper", "topk", "random") if c in complete]
    if "recommended" in headline and moonshot:
        out += ["", "## Recommended vs the paper's configuration, the baselines and the moonshot: PSNR (dB)", ""]
        out.append("| scene | ρ | " + " | ".join(headline) + " | moonshot | recommended - paper | recommended - best baseline |")
        out.append("|---|---:|" + "---:|" * (len(headline) + 3))
        for s_ in scenes:
            for q in ratios:
                cells = [_f(get[(s_, c, q)]["psnr"]) for c in headline]
                rec = get[(s_, "recommended", q)]["psnr"]
                gain = _f(rec - get[(s_, "paper", q)]["psnr"]) if "paper" in headline else "-"
                base = [get[(s_, c, q)]["psnr"] for c in ("topk", "random") if c in headline]
                margin = _f(rec - max(base)) if base else "-"
                out.append(f"| {s_} | {q:g} | " + " | ".join(cells) + f" | {_f(moonshot.get(s_, {}).get(str(q)))} | {gain} | {margin} |")
    out += ["", "## PSNR (dB) per scene", ""]
    header = "| scene | ρ | " + " | ".join(configs) + (" | moonshot |" if moonshot else " |")
    out.append(header)
    out.append("|---|---:|" + "---:|" * (len(configs) + (1 if moonshot else 0)))
    for s in scenes:
        for q in ratios:
            cells = [_f(get[(s, c, q)]["psnr"]) if (s, c, q) in get else "" for c in configs]
            if moonshot:
                cells.append(_f(moonshot.get(s, {}).get(str(q))))
            out.append(f"| {s} | {q:g} | " + " | ".join(cells) + " |")
    out += ["", "## Full table", "", "| scene | ρ | config | splats | PSNR | SSIM | FG-PSNR | colour shift R G B | seconds |", "|---|---:|---|---:|---:|---:|---:|---|---:|"]
    for s in scenes:
        for q in ratios:
            for c in configs:
                r = get.get((s, c, q))
                if r is None:
                    continue
                shift = " ".join("-" if v is None or math.isnan(v) else f"{v:+.4f}" for v in r["colour_shift"])
                out.append(f"| {s} | {q:g} | {c} | {r['count']:,} | {_f(r['psnr'])} | {_f(r['ssim'], 4)} | {_f(r['fg_psnr'])} | {shift} | {_f(r['seconds'], 2)} |")
    return "\n".join(out) + "\n"


# Best other tool, PSNR at 16 views 256^2, black background (from the issue).
MOONSHOT = {
    "guitar": {"0.1": 35.6, "0.01": 30.5, "0.001": 28.0},
    "plant": {"0.1": 31.5, "0.01": 23.8, "0.001": 19.2},
    "statue_st_peter": {"0.1": 33.2, "0.01": 26.6, "0.001": 22.4},
    "playbot": {"0.1": 30.1, "0.01": 26.5, "0.001": 23.5},
    "fruit_drops_sh3": {"0.1": 37.3, "0.01": 23.3, "0.001": 14.0},
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes_dir", type=Path, nargs="?", help="folder of .ply scenes (docs/scenes.md: the published ones)")
    parser.add_argument("-o", "--out", type=Path, required=True, help="output folder (sweep.jsonl, sweep.md)")
    parser.add_argument("--configs", default=",".join(DEFAULT_CONFIGS), help=f"comma-separated, from: {', '.join(CONFIGS)}")
    parser.add_argument("--scenes", help="comma-separated scene names (file stems); default: every .ply in the folder")
    parser.add_argument("--define", action="append", default=[], metavar="NAME=KEY:VALUE,...",
                        help="an extra NanoGS configuration: the paper's with changes, e.g. "
                        "'mine=operator:coverage,cost:runnalls,cost.mass_exponent:0.5' (cost.NAME sets a field of the "
                        "cost object; repeatable); run it by naming it in --configs")
    parser.add_argument("--ratios", default=",".join(f"{q:g}" for q in RATIOS))
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--keep-ply", action="store_true", help="also write every result as OUT/ply/<scene>_<config>_<ratio>.ply")
    parser.add_argument("--force", action="store_true", help="rerun (scene, config) pairs already in the JSON lines")
    parser.add_argument("--table-only", action="store_true", help="only rewrite OUT/sweep.md from OUT/sweep.jsonl")
    args = parser.parse_args(argv)

    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "sweep.jsonl"
    if not args.table_only:
        if args.scenes_dir is None:
            parser.error("give the scenes folder")
        for definition in args.define:
            name, _, body = definition.partition("=")
            changes = {}
            cost_params = {}
            for item in filter(None, body.split(",")):
                key, _, value = item.partition(":")
                if key.startswith("cost."):  # experimental cost parameters (a cost class taking them)
                    cost_params[key[5:]] = float(value) if "." in value else int(value)
                    continue
                if key not in PAPER:
                    parser.error(f"--define {definition!r}: unknown key {key!r}")
                changes[key] = None if value == "None" else _setting(PAPER[key], value, parser, definition)
            if cost_params:
                base = COSTS[changes.get("cost", "idiv")]
                cost_name = changes.get("cost", "idiv") + "(" + ",".join(f"{k}={v}" for k, v in sorted(cost_params.items())) + ")"
                COSTS[cost_name] = functools.partial(_with_params, base, cost_params)
                config_module.COST_NAMES += (cost_name,)  # an experimental cost name SimplifyConfig accepts
                changes["cost"] = cost_name
            CONFIGS[name.strip()] = nanogs(**changes)
        configs = [c.strip() for c in args.configs.split(",") if c.strip()]
        unknown = [c for c in configs if c not in CONFIGS]
        if unknown:
            parser.error(f"unknown configurations: {', '.join(unknown)}")
        ratios = [float(q) for q in args.ratios.split(",")]
        paths = sorted(args.scenes_dir.glob("*.ply"))
        if args.scenes:
            wanted = [s.strip() for s in args.scenes.split(",")]
            paths = [p for p in paths if p.stem in wanted]
        device = resolve_device(args.device)
        load_kernels(device, ALL_MODULES)  # as the commands load them (shipped, or compiled once), outside every timing
        keep_dir = None
        if args.keep_ply:
            keep_dir = args.out / "ply"
            keep_dir.mkdir(exist_ok=True)
        done = {(r["scene"], r["config"], json.dumps(r["spec"], sort_keys=True), r["ratio"]) for r in load_rows(log)}
        git = commit()
        for path in paths:
            scene = path.stem
            todo = [c for c in configs if args.force or any((scene, c, json.dumps(CONFIGS[c], sort_keys=True), q) not in done for q in ratios)]
            if not todo:
                continue
            splats = load_ply(path, device=device)
            cameras = orbit_cameras(splats, views=args.views, size=args.size)
            view_names = [c.name for c in cameras]
            ref_images = render_all(splats, cameras)
            for config in todo:
                started = time.perf_counter()
                rows = run_config(scene, splats, config, CONFIGS[config], ratios, cameras, ref_images, view_names, device, keep_dir)
                with log.open("a") as f:
                    for r in rows:
                        r.update({"views": args.views, "size": args.size, "device": str(device), "commit": git})
                        f.write(json.dumps(r) + "\n")
                summary = "  ".join(f"{r['ratio']:g}: {r['psnr']:.2f}" for r in rows)
                print(f"{scene:>16} {config:>14}  {summary}  ({time.perf_counter() - started:.1f} s)", file=sys.stderr, flush=True)
    (args.out / "sweep.md").write_text(markdown(load_rows(log), MOONSHOT))
    print(f"wrote {args.out / 'sweep.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
