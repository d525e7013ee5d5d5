"""A few dozen cases of the fuzz corpus (tools/fuzz_corpus.py) through the CLI on the CPU, each
(simplify and info) under a real time limit in a worker process that is killed on overrun: a clean
refusal (exit 2, one error line, nothing written, the input unchanged) or a valid result (the
budget's exact count, finite values). The whole corpus, on any device, is tools/fuzz_run.py's job."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
from importlib import resources
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "tools"))

from fuzz_corpus import corpus  # noqa: E402

SAMPLE = Path(str(resources.files("nanogs_warp.data") / "plant_crop.ply"))
SPLATS = 4000  # of the sample, and of the generated SH-3 scene
STRIDE = 13  # every 13th case, plus the inputs that once made the kNN spin
ALWAYS = (
    "one splat at z = 1e20",
    "every splat at one position",
    "half of the splats at one position",
    "coordinates from random float32 bits",
)
LIMIT_S = 30.0  # per case; a clean run of these scenes takes well under a second, warm
RATIO = 0.1


def selected_cases() -> list[tuple[str, object]]:
    picked = []
    for index, (seed_name, case) in enumerate(corpus(SAMPLE.read_bytes(), seed=0, splats=SPLATS)):
        if index % STRIDE == 0 or case.what in ALWAYS:
            picked.append((f"{index:03d}_{seed_name}_{case.family}", case))
    return picked


CASES = selected_cases()


# Runs in a child process, which the test kills if a case overruns its limit (a kernel that spins
# cannot be stopped from inside its process): reads case paths from stdin, runs simplify and info
# on each through the CLI in-process, and answers one JSON line per case with what is wrong ("" if
# nothing).
WORKER = """
import hashlib, json, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from typer.testing import CliRunner
from fuzz_run import check_refusal, check_simplified
from nanogs_warp.cli.app import app
ratio = float(sys.argv[2])
runner = CliRunner()
for line in sys.stdin:
    source = Path(line.strip())
    before = hashlib.sha256(source.read_bytes()).hexdigest()
    out_dir = source.parent / (source.stem + "_out")
    out_dir.mkdir()
    output = out_dir / "o.ply"
    r = runner.invoke(app, ["simplify", str(source), "-o", str(output), "--ratio", str(ratio), "--device", "cpu", "--json"])
    leftovers = sorted(p.name for p in out_dir.iterdir())
    if r.exit_code == 2:
        simplify = check_refusal(2, r.stderr, leftovers)
    elif r.exit_code == 0:
        simplify = check_simplified(output, json.loads(r.stdout), ratio, leftovers)
    else:
        simplify = f"exit code {r.exit_code}: {r.stderr.strip()}"
    i = runner.invoke(app, ["info", str(source), "--json"])
    if i.exit_code == 2:
        info = check_refusal(2, i.stderr, [])
    elif i.exit_code == 0 and not i.stderr:
        info = "" if json.loads(i.stdout)["count"] >= 0 else "no count"
    else:
        info = f"exit code {i.exit_code}: {i.stderr.strip()}"
    changed = hashlib.sha256(source.read_bytes()).hexdigest() != before
    print(json.dumps({"simplify": simplify, "info": info, "changed": changed}), flush=True)
"""


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory) -> dict[str, dict | str]:
    """Case name -> the worker's answer, or why there is none (killed past the limit, or not reached)."""
    folder = tmp_path_factory.mktemp("corpus")
    tools = str(Path(__file__).parents[1] / "tools")
    worker = subprocess.Popen([sys.executable, "-c", WORKER, tools, str(RATIO)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in worker.stdout], daemon=True).start()
    answers: dict[str, dict | str] = {}
    try:
        for name, case in CASES:
            source = folder / f"{name}.ply"
            source.write_bytes(case.data)
            worker.stdin.write(f"{source}\n")
            worker.stdin.flush()
            try:
                answers[name] = json.loads(lines.get(timeout=LIMIT_S))
            except queue.Empty:
                answers[name] = f"still running after {LIMIT_S:.0f} s ({case.what}); the worker was killed"
                break
    finally:
        worker.kill()
        worker.wait()
    for name, _ in CASES:
        answers.setdefault(name, "not reached: an earlier case overran its limit")
    return answers


def test_the_selection_covers_every_family():
    assert len(CASES) >= 30
    families = {case.family for _, case in CASES}
    assert families == {"header", "truncate", "corrupt", "extreme", "geometry"}


@pytest.mark.parametrize("name, case", CASES, ids=[name for name, _ in CASES])
def test_corpus_case(name, case, outcomes):
    answer = outcomes[name]
    assert isinstance(answer, dict), answer
    assert not answer["changed"], f"{case.what}: the input changed"
    assert answer["simplify"] == "", f"{case.what}: simplify: {answer['simplify']}"
    assert answer["info"] == "", f"{case.what}: info: {answer['info']}"
