"""One scene of a batch, as a worker (a local process or a Ray task) runs it: hash the input, skip it
when its record says the outputs are up to date, else simplify it to every budget in one
progressive run, write each output atomically and the record last.

The record, ``OUTDIR/<rel>/<stem>.nanogs.json``, holds the input's size and hash (SHA-256 over its
1 MiB pieces' SHA-256, :class:`~nanogs_warp.io.ply_read.PieceHash`, hashed on every reader thread), the options
and tool version the outputs were made with, and each output's budget, count and size. It is
deleted before a scene is redone and written (atomically) only after every output, so a record
always describes finished outputs: a run killed at any point leaves no record that lies.
"""

from __future__ import annotations

import json
import os
import stat
import time
import traceback
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .. import __version__
from ..errors import InputError, debugging, out_of_memory, package_warnings
from .scenes import SceneJob

RECORD_FORMAT = 2  # 2: the input's hash is its PieceHash ("sha256_pieces"), no longer its plain SHA-256


@dataclass
class SceneResult:
    """What became of one scene; ``status`` is ``done``, ``skipped`` (up to date) or ``failed``.
    ``stages`` holds the seconds its stages took: read (hash and parse), simplify, write."""

    input: str
    relative: str
    status: str
    device: str
    seconds: float = 0.0
    input_count: int | None = None
    outputs: list[dict] = field(default_factory=list)  # {"path", "budget", "count"}
    error: str | None = None
    notes: list[str] = field(default_factory=list)  # rows dropped on load, what the output format drops
    stages: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict:
        return asdict(self)


def input_hash(path: Path) -> str:
    """The file's hash as records keep it (:class:`~nanogs_warp.io.ply_read.PieceHash`), read on
    several threads."""
    from ..io.ply_read import file_piece_hash

    return file_piece_hash(path)


@dataclass
class LoadedScene:
    """A scene between its stages: read (``splats`` on the host, or ``result`` already final when
    it was skipped or failed), then simplified (``simplified``: (target, splats on the host,
    budgets)), then written."""

    job: SceneJob
    result: SceneResult
    size: int = 0
    sha: str = ""
    splats: object = None
    simplified: list = field(default_factory=list)
    device_kind: str = ""
    seconds: float = 0.0  # time spent on the scene so far, over all its stages

    @property
    def final(self) -> bool:
        """Nothing left to do but report: skipped, or failed."""
        return self.result.error is not None or self.result.status == "skipped"


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
    scene = read_scene(job, force, device_label or str(device))
    simplify_scene(scene, device, on_pass)
    return write_scene(scene)


def read_scene(job: SceneJob, force: bool, label: str) -> LoadedScene:
    """Stage 1: the skip test, then the input on the host. The input is read once when it has no
    matching record (hashed as it is parsed), twice only when a record must be checked and turns
    out stale. Never raises."""
    scene = LoadedScene(job, SceneResult(str(job.input), job.relative, "failed", label))
    with _stage(scene, "read"):
        _read(scene, force)
    return scene


def simplify_scene(scene: LoadedScene, device, on_pass: Callable | None = None) -> None:
    """Stage 2: every budget in one progressive run on ``device``; the results come back to the
    host. Timed as three stages: ``upload`` (the input to the device), ``simplify`` and
    ``download`` (the results back to the host)."""
    if scene.final:
        return
    with _stage(scene, "upload"):
        job, splats = scene.job, scene.splats
        scene.splats = None  # the host copy is not needed again
        scene.device_kind = getattr(device, "name", str(device))
        on_device = splats.to(device)
        del splats
        _synchronize(device)
    if scene.final:  # it failed (out of device memory, say)
        return
    download = 0.0
    with _stage(scene, "simplify"):
        by_target: dict[int, list] = {}
        for budget in job.budgets:
            by_target.setdefault(budget.target(on_device.count), []).append(budget)
        views = None  # the input's renders that refinement trains on: made once, shared by every budget
        if job.refine_steps > 0:
            from ..refinement.config import RefineConfig
            from ..refinement.refine import ReferenceViews

            views = ReferenceViews(on_device, RefineConfig(steps=job.refine_steps, size=job.refine_size, seed=job.config.seed))
        with package_warnings(lambda line: _note_once(scene.result, line)):  # the scene's notes, not stderr
            download = _simplify_budgets(scene, on_device, by_target, views, on_pass)
        del views
    if "simplify" in scene.result.stages:
        scene.result.stages["simplify"] = round(scene.result.stages["simplify"] - download, 4)
        scene.result.stages["download"] = round(download, 4)


def _simplify_budgets(scene: LoadedScene, on_device, by_target: dict, views, on_pass) -> float:
    """``simplify_scene``'s progressive run: each result (its SH degree dropped, refined, where
    asked) copied to the host; returns the seconds the copies took."""
    from ..refinement.refine import refine_with_report
    from ..refinement.simplify import simplify_progressively

    job = scene.job
    download = 0.0
    for target, simplified in simplify_progressively(on_device, list(by_target), job.config, on_pass=on_pass):
        if job.sh_degree is not None:  # the bands above it dropped from the output, before refinement
            simplified = simplified.with_sh_degree(job.sh_degree)
        if views is not None:
            simplified = refine_with_report(simplified, on_device, views.config, views=views)[0]
        # to the host here, so that the writer thread never touches the GPU (and its memory is freed)
        begun = time.perf_counter()
        scene.simplified.append((target, simplified.to("cpu"), by_target[target]))
        download += time.perf_counter() - begun
    return download


def _synchronize(device) -> None:
    if not getattr(device, "is_cpu", True):
        import warp as wp

        wp.synchronize_device(device)


def write_scene(scene: LoadedScene) -> SceneResult:
    """Stage 3: each output atomically, then the record; returns the scene's final result."""
    if not scene.final:
        with _stage(scene, "write"):
            _write(scene)
        scene.simplified = []
    result = scene.result
    if result.error is not None:
        result.status = "failed"
    result.seconds = round(scene.seconds, 4)
    return result


@contextmanager
def _stage(scene: LoadedScene, name: str):
    """Times a stage into the result, and turns any error into the scene's failure."""
    started = time.perf_counter()
    try:
        yield
    except InputError as e:
        scene.result.error = str(e)
    except Exception as e:  # noqa: BLE001 - one bad scene must not stop the batch
        if debugging():
            traceback.print_exc()
        scene.result.error = out_of_memory(e) or f"{type(e).__name__}: {' '.join(str(e).split())}"
    finally:
        seconds = time.perf_counter() - started
        scene.seconds += seconds
        scene.result.stages[name] = round(seconds, 4)
        if scene.result.error is not None:
            scene.splats, scene.simplified = None, []


def _read(scene: LoadedScene, force: bool) -> None:
    from ..io import detect_format, load_splats
    from ..io.ply import load_ply
    from ..io.ply_read import PieceHash

    job, result = scene.job, scene.result
    spin_if_asked(job)
    scene.size = _input_status(job).st_size
    record, scene.sha, why = _freshness(job, scene.size, force)
    if why is None:
        result.status = "skipped"
        result.input_count = record["input_count"]
        order = [b.label for b in job.budgets]  # as given this time (the record may hold another order)
        result.outputs = [{"path": str(job.out_dir / o["path"]), "budget": o["budget"], "count": o["count"]}
                          for o in sorted(record["outputs"], key=lambda o: order.index(o["budget"]))]  # fmt: skip
        return

    check_output_names(job)
    _remove_leftovers(job)  # the old record first: from here on, no record describes these outputs
    if detect_format(job.input) == "ply":  # hashed as it is parsed, by the threads that read it
        hasher = None if scene.sha else PieceHash(scene.size)
        scene.splats = load_ply(job.input, device="cpu", drop_invalid=job.drop_invalid, on_drop=result.notes.append,
                                file_hash=hasher)  # fmt: skip
        if hasher is not None:
            scene.sha = hasher.hexdigest()
    else:
        if not scene.sha:
            scene.sha = input_hash(job.input)
        scene.splats = load_splats(job.input, device="cpu", drop_invalid=job.drop_invalid, on_drop=result.notes.append)
    result.input_count = scene.splats.count


def _write(scene: LoadedScene) -> None:
    from ..io import input_files, save_splats
    from ..io.ply_write import OutputSet, remove_if_still

    job, result = scene.job, scene.result
    files = OutputSet(keep=input_files(job.input))  # the scene's outputs appear together, or (a failure part way) none of them
    try:
        files.make_folder(job.out_dir)  # here, and removed with the outputs: a scene that fails or is stopped leaves no empty folder
        outputs = []
        for _, simplified, budgets in scene.simplified:
            for budget in budgets:
                save_splats(simplified, job.output_path(budget), job.output_format, on_loss=lambda line: _note_once(result, line),
                            outputs=files)  # fmt: skip
                outputs.append({"path": job.output_path(budget).name, "budget": budget.label, "count": simplified.count})
        published = files.publish()  # what this run put where: only those files are taken back below
    except BaseException:
        files.discard()
        raise
    for out in outputs:
        out["bytes"] = (job.out_dir / out["path"]).stat().st_size
    outputs.sort(key=lambda o: [b.label for b in job.budgets].index(o["budget"]))
    record = {
        "format": RECORD_FORMAT,
        "tool": "nanogs-warp",
        "version": __version__,
        "input": {"path": os.path.abspath(job.input), "relative": job.relative, "bytes": scene.size, "sha256_pieces": scene.sha},
        "options": job.options(),
        "input_count": result.input_count,
        "outputs": outputs,
        "device": result.device,
        "device_kind": scene.device_kind,  # e.g. "NVIDIA H100 80GB HBM3" or the CPU's
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    try:
        write_json_atomic(job.record_path, record)
    except OSError as e:  # outputs without their record would be redone anyway: none stays (a full disk)
        for path, identity in published:  # this run's files, not another node's written there since (a shared folder)
            remove_if_still(path, identity)
        raise InputError(f"cannot write its record {job.record_path.name}: {e.strerror or e}") from e
    result.status = "done"
    result.outputs = [{"path": str(job.out_dir / o["path"]), "budget": o["budget"], "count": o["count"]} for o in outputs]


def _note_once(result: SceneResult, line: str) -> None:
    """Keeps what an output format drops once per scene, not once per budget."""
    what = line.split(": ", 1)[-1]
    if all(n.split(": ", 1)[-1] != what for n in result.notes):
        result.notes.append(line)


# Tests only: a worker that reads a scene whose relative path is this variable's value spins for
# ever (holding the CPU, deaf to everything but SIGKILL), as a scene whose kernel never ends would.
SPIN_SCENE_VARIABLE = "NANOGS_WARP_TEST_SPIN_SCENE"


def spin_if_asked(job: SceneJob) -> None:
    if os.environ.get(SPIN_SCENE_VARIABLE) == job.relative:
        while True:
            pass


RECORD_LIMIT = 16 << 20  # a scene's record is a few kB; a larger file (or no regular file) is not one


def read_record(path: Path) -> dict | None:
    """The scene's record, or None where there is none that can be read (the scene is then redone):
    a FIFO or a device in its place is not read, nor more than RECORD_LIMIT bytes."""
    from ..errors import InputError
    from ..io.common import read_file_bytes

    try:
        record = json.loads(read_file_bytes(path, RECORD_LIMIT).decode("utf-8"))
    except (InputError, OSError, ValueError, RecursionError):
        return None
    return record if isinstance(record, dict) else None


def record_mismatch(record: dict | None, job: SceneJob, size: int, sha: str | None, options: dict) -> str | None:
    """Why ``record`` does not show the scene up to date, in a few words; None when it does: when it
    was written by this tool version for these exact input bytes and options, and every output it
    lists is still there with its recorded size (``sha`` None: any input with this size)."""
    if record is None:
        return "no record"
    try:
        if record["format"] != RECORD_FORMAT or record["version"] != __version__:
            return "made by another version"
        if _in_any_order(record["options"]) != _in_any_order(options):
            return "other budgets or options"
        if record["input"]["bytes"] != size or (sha is not None and record["input"]["sha256_pieces"] != sha):
            return "the input changed"
        outputs = record["outputs"]
        if not (_whole(record["input_count"]) and all(_whole(o["count"]) and _whole(o["bytes"]) and _plain_name(o["path"])
                                                       for o in outputs)):  # fmt: skip
            return "a record edited by hand"
        if sorted(o["budget"] for o in outputs) != sorted(b.label for b in job.budgets):
            return "other budgets"
        names = {b.label: job.output_path(b).name for b in job.budgets}
        if any(o["path"] != names[o["budget"]] for o in outputs):  # a record naming other files
            return "a record edited by hand"
        if not all((job.out_dir / o["path"]).stat().st_size == o["bytes"] for o in outputs):
            return "an output changed"
    except (KeyError, TypeError):
        return "a record edited by hand"
    except OSError:
        return "an output is missing"
    return None


def _in_any_order(options):
    """``options`` with its budgets sorted: the same budgets in another order make the same outputs
    (one progressive run), so they need no new run. Anything that is not a record's options as
    ``SceneJob.options`` writes them comes back as it is (and then differs)."""
    if not isinstance(options, dict) or not isinstance(options.get("budgets"), list):
        return options
    return {**options, "budgets": sorted(options["budgets"], key=lambda b: json.dumps(b, sort_keys=True))}


def planned(job: SceneJob, force: bool) -> tuple[str, str | None]:
    """What a run would do with the scene, as ``_read`` decides it (the input hashed where its
    record could match): ("skip", None) when it is up to date, ("run", why) or ("fail", why)."""
    try:
        status = _input_status(job)
        if not stat.S_ISREG(status.st_mode):  # a folder, a FIFO, a device: a run refuses it (open_regular)
            return "fail", "not a regular file"
        _, _, why = _freshness(job, status.st_size, force)
        if why is not None:
            check_output_names(job)
    except InputError as e:
        return "fail", str(e)
    return ("skip", None) if why is None else ("run", why)


def check_output_names(job: SceneJob) -> None:
    """An InputError where an output's or the record's name is too long to be written (its temporary
    file's name is longer still), or names a folder or another file that is no regular file (a
    FIFO, a device) that writing would refuse: found by ``--dry-run`` as by a run, before any work."""
    from ..io.ply_write import check_name_length, refuse_no_file, through_links

    for path in (*(job.output_path(b) for b in job.budgets), job.record_path):
        check_name_length(path)
    try:
        if job.record_path.is_dir():
            raise InputError(f"its record {job.record_path} is a folder; move it away")
        for path in map(job.output_path, job.budgets):
            refuse_no_file(through_links(path))
    except OSError as e:  # a folder on the way it may not search: this scene fails, not the batch
        raise InputError(f"cannot check its outputs: {e.strerror or e}") from None


def _input_status(job: SceneJob) -> os.stat_result:
    """The scene file's status, or an InputError saying why it cannot be read."""
    try:
        return job.input.stat()
    except FileNotFoundError:
        raise InputError("no such file") from None
    except OSError as e:
        raise InputError(f"cannot read the file: {e.strerror or e}") from None


def _freshness(job: SceneJob, size: int, force: bool) -> tuple[dict | None, str, str | None]:
    """(the scene's record, the input's hash or "" where none was needed, why its outputs are not up
    to date or None where they are). The record is compared without the hash first; the input is
    hashed only where everything else matches (an InputError where it cannot be read)."""
    if force:
        return None, "", "--force"
    options = job.options()
    record = read_record(job.record_path)
    why = record_mismatch(record, job, size, None, options)
    if why is not None:
        return record, "", why
    try:
        sha = input_hash(job.input)
    except OSError as e:
        raise InputError(f"cannot read the file: {e.strerror or e}") from None
    return record, sha, record_mismatch(record, job, size, sha, options)


def _whole(value) -> bool:
    """A count a record may hold: a whole number from 0 to 2^63."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 1 << 63


def _plain_name(value) -> bool:
    """An output's name in a record: a file name beside the record, nothing else."""
    return isinstance(value, str) and value not in ("", ".", "..") and not any(c in value for c in "/\\\0")


def write_json_atomic(path: Path, data: dict) -> None:
    """Writes ``data`` to a temporary file beside ``path`` and renames it into place."""
    from ..io.ply_write import temporary_path, through_links

    tmp = temporary_path(path := through_links(path))
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
    """Deletes the scene's record and the temporary files a killed run of it may have left beside
    each output (``remove_stale_temporaries``: only those whose writing process is gone, so that
    another run writing the same scene at the same time keeps its own)."""
    if not job.out_dir.is_dir():
        return
    job.record_path.unlink(missing_ok=True)  # not a folder: check_output_names refused that first
    from ..io.ply_write import remove_stale_temporaries

    remove_stale_temporaries([job.record_path, *(job.output_path(b) for b in job.budgets)])
