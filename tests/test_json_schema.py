"""Every --json output against its layout in docs/json.md, with a small checker of those layouts."""

import json
import re
from pathlib import Path

import pytest
from scene_factory import random_splats_ply
from typer.testing import CliRunner

from nanogs_warp.cli.app import app

DOC = Path(__file__).resolve().parent.parent / "docs" / "json.md"
TYPES = {
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "string": lambda v: isinstance(v, str),
    "bool": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    "list": lambda v: isinstance(v, list),
    "object": lambda v: isinstance(v, dict),
}


def documented_layouts() -> dict[str, object]:
    blocks = re.findall(r"```json schema=(\w+)\n(.*?)```", DOC.read_text(encoding="utf-8"), flags=re.DOTALL)
    return {name: json.loads(body) for name, body in blocks}


def problems(value, layout, where="$") -> list[str]:
    """Where ``value`` departs from ``layout`` (empty: it conforms)."""
    if isinstance(layout, str):
        kinds = layout.split("|")
        unknown = [k for k in kinds if k not in TYPES]
        if unknown:
            return [f"{where}: unknown type {unknown} in the layout"]
        return [] if any(TYPES[k](value) for k in kinds) else [f"{where}: {value!r} is not {layout}"]
    if isinstance(layout, list):
        if not isinstance(value, list):
            return [f"{where}: expected a list, got {value!r}"]
        return [p for k, item in enumerate(value) for p in problems(item, layout[0], f"{where}[{k}]")]
    if not isinstance(value, dict):
        return [f"{where}: expected an object, got {value!r}"]
    if set(layout) == {"*"}:
        return [p for key, item in value.items() for p in problems(item, layout["*"], f"{where}.{key}")]
    required = {k for k in layout if not k.endswith("?")}
    allowed = {k.rstrip("?"): t for k, t in layout.items()}
    found = [f"{where}: missing {k!r}" for k in sorted(required - value.keys())]
    found += [f"{where}: undocumented {k!r}" for k in sorted(value.keys() - allowed.keys())]
    for key in sorted(value.keys() & allowed.keys()):
        found += problems(value[key], allowed[key], f"{where}.{key}")
    return found


def test_checker_catches_departures():
    layout = {"a": "int", "b?": ["string"], "c": {"*": "number|null"}}
    assert problems({"a": 1, "c": {"x": None, "y": 2.5}}, layout) == []
    assert problems({"a": 1, "b": ["x"], "c": {}}, layout) == []
    assert problems({"a": True, "c": {}}, layout) == ["$.a: True is not int"]
    assert problems({"c": {}}, layout) == ["$: missing 'a'"]
    assert problems({"a": 1, "c": {}, "d": 0}, layout) == ["$: undocumented 'd'"]
    assert problems({"a": 1, "b": [3], "c": {"x": "s"}}, layout) == ["$.b[0]: 3 is not string", "$.c.x: 's' is not number|null"]


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """The four commands' --json output on one small scene."""
    root = tmp_path_factory.mktemp("json")
    scenes = root / "scenes"
    scenes.mkdir()
    random_splats_ply(scenes / "a.ply", 300, sh_degree=1, seed=1)
    runner = CliRunner()

    def run(*args):
        result = runner.invoke(app, [str(a) for a in args])
        assert result.exit_code == 0, result.output
        return json.loads(result.stdout)

    return {
        "simplify": run("simplify", scenes / "a.ply", "-o", f"{root / 'out'}/", "--ratio", "0.1,0.01", "--device", "cpu", "--json"),
        "info": run("info", scenes / "a.ply", "--json"),
        "eval": run("eval", scenes / "a.ply", root / "out" / "a_0.1.ply", root / "out" / "a_0.01.ply", "--views", "2",
                    "--size", "16", "--device", "cpu", "--json", "--images", root / "images"),  # fmt: skip
        "batch": run("batch", scenes, "-o", root / "batch", "--ratio", "0.1", "--devices", "cpu", "--json"),
        "batch_dry_run": run("batch", scenes, "-o", root / "batch", "--ratio", "0.1,0.5", "--dry-run", "--json"),
    }


@pytest.mark.parametrize("command", ["simplify", "info", "eval", "batch", "batch_dry_run"])
def test_json_output_matches_its_documented_layout(outputs, command):
    layouts = documented_layouts()
    assert set(layouts) == {"simplify", "info", "eval", "batch", "batch_dry_run"}
    out = outputs[command]
    assert problems(out, layouts[command]) == []
    assert out["schema"] == 1 and out["command"] == command.removesuffix("_dry_run")


def test_json_paths_are_absolute_and_settings_echoed(outputs):
    simplify, info, evaluation, batch = (outputs[c] for c in ("simplify", "info", "eval", "batch"))
    paths = [simplify["input"], *(o["path"] for o in simplify["outputs"]), info["path"], evaluation["reference"]["path"]]
    paths += [t["path"] for t in evaluation["tests"]] + [t["images"] for t in evaluation["tests"]]
    paths += [batch["output"], *(s["input"] for s in batch["scenes"])]
    paths += [o["path"] for s in batch["scenes"] for o in s["outputs"]]
    for path in paths:
        assert Path(path).is_absolute() and Path(path).exists(), path
    assert simplify["settings"]["k"] == 24 and simplify["settings"]["operator"] == "coverage"
    assert simplify["settings"]["cost"] == "field" and simplify["settings"]["device"] == "cpu"
    assert simplify["settings"]["seed"] == 0
    assert batch["settings"]["devices"] == "cpu" and batch["settings"]["operator"] == "coverage"
    assert evaluation["settings"]["views"] == 2 and evaluation["settings"]["cameras"] == "orbit"


def test_file_names_that_are_not_utf8_stay_strict_json():
    """Python holds a name's undecodable bytes as lone surrogates, which json.dumps wrote as
    "\\udcff" escapes that strict readers refuse: they are written as the text \\xff."""
    import json
    import os

    from nanogs_warp.cli.options import json_text

    name = os.fsdecode(b"/data/a\xff.ply")
    text = json_text({"input": name, name: [name], "odd": "\ud800"})
    assert "\\udcff" not in text and "\\ud800" not in text.replace("\\\\ud800", "")
    out = json.loads(text)
    assert out["input"] == "/data/a\\xff.ply" and out["/data/a\\xff.ply"] == ["/data/a\\xff.ply"]
    text.encode("utf-8")  # every character encodes: no lone surrogate left
