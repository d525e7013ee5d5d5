"""One scene of a batch, as a worker (a local process or a Ray task) runs it: hash the input, skip it
when its record says the outputs are up to date, else simplify it to every budget in one
progressive run, write each output atomically and the record last.

The record, ``OUTDIR/<rel>/<stem>.nanogs.json``, holds the input's size and SHA-256, the options
and tool version the outputs were made with, and each output's budget, count and size. It is
deleted before a scene is redone and written (atomically) only after every output, so a record
always describes finished outputs: a run killed at any point leaves no record that lies.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from . import __version__
from .batch_scenes import SceneJob
from .errors import InputError

RECORD_FORMAT = 1


@dataclass
class SceneResult:
    """What became of one scene; ``status`` is ``done``, ``skipped`` (up to date) or ``failed``."""

    input: str
    relative: str
    status: str
    device: str
    seconds: float = 0.0
    input_count: int | None = None
    outputs: list[dict] = field(default_factory=list)  # {"path", "budget", "count"}
    error: str | None = None

    def to_json(self) -> dict:
        return asdict(self)


def file_sha256(path: Path) -> str:
    """The file's SHA-256, read in blocks (constant memory)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def process_scene(
    job: SceneJob,
    device,
    force: bool = False,
    device_label: str | None = None,
    on_pass: Callable | None = None,
) -> SceneResult:
    """Simplifies ``job`` on the Warp ``device`` (Warp already initialised), or skips it when its
    record is up to date and ``force`` is false. Never raises for a bad scene: any error, out of
    memory included, comes back as a ``failed`` result."""
    started = time.perf_counter()
    label = device_label or str(device)
    result = SceneResult(str(job.input), job.relative, "failed", label)
    try:
        _run(job, device, force, result, on_pass)
    except InputError as e:
        result.error = str(e)
    except MemoryError:
        result.error = "out of memory"
    except Exception as e:  # noqa: BLE001 - one bad scene must not stop the batch
        if os.environ.get("NANOGS_DEBUG"):
            traceback.print_exc()
        result.error = f"{type(e).__name__}: {' '.join(str(e).split())}"
    if result.error is not None:
        result.status = "failed"
    result.seconds = round(time.perf_counter() - started, 4)
    return result


def _run(job: SceneJob, device, force: bool, result: SceneResult, on_pass) -> None:
    from .pipeline import simplify_progressively
    from .ply import load_ply, save_ply

    try:
        size = job.input.stat().st_size
        sha = file_sha256(job.input)
    except FileNotFoundError:
        raise InputError(f"{job.relative}: no such file") from None
    except OSError as e:
        raise InputError(f"{job.relative}: cannot read the file: {e.strerror or e}") from None
    options = job.options()
    if not force:
        record = read_record(job.record_path)
        if record_matches(record, job, size, sha, options):
            result.status = "skipped"
            result.input_count = record["input_count"]
            result.outputs = [{"path": str(job.out_dir / o["path"]), "budget": o["budget"], "count": o["count"]}
                              for o in record["outputs"]]  # fmt: skip
            return

    job.out_dir.mkdir(parents=True, exist_ok=True)
    _remove_leftovers(job)  # the old record first: from here on, no record describes these outputs
    splats = load_ply(job.input, device="cpu", drop_invalid=job.drop_invalid)
    result.input_count = splats.count
    by_target: dict[int, list] = {}
    for budget in job.budgets:
        by_target.setdefault(budget.target(splats.count), []).append(budget)
    outputs = []
    on_device = splats.to(device)
    for target, simplified in simplify_progressively(on_device, list(by_target), job.config, on_pass=on_pass):
        if job.refine_steps > 0:
            from .refine import RefineConfig, refine_with_report

            config = RefineConfig(steps=job.refine_steps, size=job.refine_size, seed=job.config.seed)
            simplified = refine_with_report(simplified, on_device, config)[0]
        for budget in by_target[target]:
            path = job.output_path(budget)
            save_ply(simplified, path)
            outputs.append({"path": path.name, "budget": budget.label, "count": simplified.count,
                            "bytes": path.stat().st_size})  # fmt: skip
    outputs.sort(key=lambda o: [b.label for b in job.budgets].index(o["budget"]))
    record = {
        "format": RECORD_FORMAT,
        "tool": "nanogs-warp",
        "version": __version__,
        "input": {"path": os.path.abspath(job.input), "relative": job.relative, "bytes": size, "sha256": sha},
        "options": options,
        "input_count": splats.count,
        "outputs": outputs,
        "device": result.device,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    write_json_atomic(job.record_path, record)
    result.status = "done"
    result.outputs = [{"path": str(job.out_dir / o["path"]), "budget": o["budget"], "count": o["count"]} for o in outputs]


def read_record(path: Path) -> dict | None:
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def record_matches(record: dict | None, job: SceneJob, size: int, sha: str, options: dict) -> bool:
    """True when ``record`` was written by this tool version for these exact input bytes and
    options, and every output it lists is still there with its recorded size."""
    try:
        if (record["format"] != RECORD_FORMAT or record["version"] != __version__ or record["options"] != options
                or record["input"]["bytes"] != size or record["input"]["sha256"] != sha):  # fmt: skip
            return False
        outputs = record["outputs"]
        if sorted(o["budget"] for o in outputs) != sorted(b.label for b in job.budgets):
            return False
        return all((job.out_dir / o["path"]).stat().st_size == o["bytes"] for o in outputs)
    except (KeyError, TypeError, OSError):
        return False


def write_json_atomic(path: Path, data: dict) -> None:
    """Writes ``data`` to a temporary file beside ``path`` and renames it into place."""
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
    try:
        with open(tmp, "x", encoding="utf-8") as f:
            json.dump(data, f, indent=2)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _remove_leftovers(job: SceneJob) -> None:
    """Deletes the scene's record and the temporary files a killed run of it may have left
    (``.<name>.<random>.tmp`` beside each output; shards never share a scene, so none is live)."""
    job.record_path.unlink(missing_ok=True)
    names = {job.record_path.name} | {job.output_path(b).name for b in job.budgets}
    for entry in os.scandir(job.out_dir):
        if entry.name.endswith(".tmp") and entry.name.startswith(".") and entry.name[1:].rsplit(".", 2)[0] in names:
            try:
                os.unlink(entry.path)
            except OSError:
                pass
