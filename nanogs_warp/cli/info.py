"""``nanogs-warp info``: what a splat file holds, as text or JSON.

Registered in ``app.py`` as ``app.command("info")(user_errors(info_command))``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..domain import LOG_SCALE_LIMIT
from . import options as opts
from .options import JSON_SCHEMA


def info_command(
    input: Annotated[Path, typer.Argument(help="A scene file: INRIA or compressed .ply, .spz, .sog, meta.json, lod-meta.json or .splat.", show_default=False, metavar="SCENE")],
    json_output: Annotated[bool, typer.Option("--json", help="Print JSON instead of text.")] = False,
) -> None:
    """Describe a 3DGS scene: count, SH degree, properties, bounds, opacity and scale statistics."""
    from ..io.scene_info import scene_info

    details = scene_info(input)
    if json_output:
        details = {"schema": JSON_SCHEMA, "command": "info", "path": str(input.resolve()), **details}
    typer.echo(opts.json_text(details) if json_output else format_info(details))


def format_info(info: dict) -> str:
    """Human-readable text for a :func:`~nanogs_warp.io.scene_info.scene_info` dict."""
    lines = [
        f"file        {info['file']} ({info['file_bytes']:,} bytes, {info['format']})",
        f"splats      {info['count']:,}" + (
            f" ({info['trailing_bytes']:,} bytes after the declared data ignored)" if info.get("trailing_bytes") else ""
        ),
        f"SH degree   {info['sh_degree']} ({3 * (info['sh_degree'] + 1) ** 2} coefficients)",
    ]
    props = info["properties"]
    lines.append(f"properties  {len(props)}: " + " ".join(_compress_names(props)))
    if info["extra_properties"]:
        lines.append(f"extras      {', '.join(info['extra_properties'])}")
    if info["model"] == "2DGS":
        lines.append("model       2DGS (no scale_2): read as flat 3DGS splats, written as 3DGS")
    box = info["bbox"]
    if box["min"] is not None:
        lines.append(f"bbox min    {_vec(box['min'])}")
        lines.append(f"bbox max    {_vec(box['max'])}")
        lines.append(f"bbox size   {_vec([hi - lo for lo, hi in zip(box['min'], box['max'])])}")
    else:
        lines.append("bbox        (no finite positions)")
    lines.append("opacity     " + _stats_text(info["opacity"]))
    lines.append("scale       " + _stats_text(info["scale"]))
    nonfinite = info["nonfinite"]
    if nonfinite:
        shown = ", ".join(f"{k} {v:,}" for k, v in nonfinite.items())
        lines.append(f"NaN/Inf     {info['nonfinite_rows']:,} splats; per property: {shown}")
    else:
        lines.append("NaN/Inf     none")
    pos, neg = info["infinite_opacity"]["+inf"], info["infinite_opacity"]["-inf"]
    if pos or neg:
        lines.append(f"opacity Inf {pos:,} logits +Inf (alpha 1), {neg:,} -Inf (alpha 0); valid")
    lines.append(f"zero quats  {info['zero_norm_quaternions']:,}")
    if info["out_of_domain"]:
        shown = ", ".join(f"{k} {v:,}" for k, v in info["out_of_domain"].items())
        lines.append(f"log-scales  {info['out_of_domain_rows']:,} splats beyond +-{LOG_SCALE_LIMIT:g}; per property: {shown}")
    for e in info["other_elements"]:
        lines.append(f"element     {e['name']} ({e['count']:,} rows: {', '.join(e['properties'])})")
    for c in info["comments"]:
        lines.append(f"comment     {c}")
    for c in info["obj_info"]:
        lines.append(f"obj_info    {c}")
    return "\n".join(lines)



def _stats_text(stats: dict | None) -> str:
    if stats is None:
        return "(no finite values)"
    return "  ".join(f"{k} {v:.4g}" for k, v in stats.items())


def _vec(v) -> str:
    return "  ".join(f"{x:+.4g}" for x in v)


def _compress_names(props: list[dict]) -> list[str]:
    """``f_rest_0..44 (f4)``-style runs instead of 45 separate names."""
    out = []
    i = 0
    while i < len(props):
        name, dtype = props[i]["name"], props[i]["dtype"]
        stem, _, num = name.rpartition("_")
        j = i + 1
        if stem and num.isdigit():
            while (j < len(props) and props[j]["dtype"] == dtype
                   and props[j]["name"] == f"{stem}_{int(num) + j - i}"):
                j += 1
        out.append(f"{name}..{int(num) + j - i - 1}:{dtype}" if j - i > 1 else f"{name}:{dtype}")
        i = j
    return out
