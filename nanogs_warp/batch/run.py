"""``nanogs-warp batch``: many scenes, every budget each, on all local devices or a Ray cluster.

The pieces: :mod:`.scenes` finds the scenes and shards them, :mod:`.work` runs one scene (resume
records included), :mod:`.local` schedules worker processes on this machine, :mod:`.ray_cluster`
Ray tasks. This module ties them together and reports: progress on stderr, the
summary table or JSON.
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import nullcontext
from pathlib import Path

from ..errors import one_line, printable
from .scenes import SceneJob, find_scenes, parse_shard, select_shard
from .work import SceneResult, planned, process_scene

__all__ = ["BatchProgress", "SceneJob", "SceneResult", "find_scenes", "format_plan", "format_summary", "parse_shard",
           "plan_batch", "process_scene", "run_batch", "select_shard", "summary_json"]  # fmt: skip


def run_batch(
    jobs: list[SceneJob],
    devices: list[str] | None = None,
    workers_per_device: int | None = 1,
    ray_address: str | None = None,
    ray_gpu: bool | None = None,
    force: bool = False,
    progress: BatchProgress | None = None,
    scene_timeout_s: float | None = None,
    readers: int | None = None,
    mps: bool = False,
) -> list[SceneResult]:
    """Simplifies every job, on local worker processes (``devices``, e.g. ``["cuda:0", "cuda:1"]``)
    or as Ray tasks (``ray_address``); returns one result per job, sorted by scene name.
    ``workers_per_device``: local worker processes per device (None: two on a GPU that holds two of
    the largest scene, else one: ``gpu_workers.auto_workers``).
    ``scene_timeout_s``: each scene's time limit (None: scaled with its size; 0: none).
    ``readers``: threads per worker that read each input (None: the cores shared out among the
    local workers, 1 to 8; a Ray task: the cores of its node, up to 8).
    ``mps``: the local GPU workers run under CUDA MPS (:func:`~nanogs_warp.batch.mps.mps_for_batch`:
    a running MPS control daemon, else one started for the batch); a GPU's workers auto then count
    as under MPS, as they do whenever such a daemon is running."""
    progress = progress or BatchProgress(len(jobs), quiet=True)
    try:
        if not jobs:
            results = []
        elif ray_address is not None:
            from .ray_cluster import run_ray

            results = run_ray(jobs, ray_address, ray_gpu, force, progress, scene_timeout_s, readers)
        else:
            from .local import run_local
            from .mps import mps_for_batch, running_mps

            devices = devices or ["cpu"]
            with mps_for_batch() if mps else nullcontext():
                under_mps = devices != ["cpu"] and (mps or running_mps() is not None)
                results = run_local(jobs, devices, workers_per_device, force, progress, scene_timeout_s, readers, under_mps)
    finally:
        progress.close()
    return sorted(results, key=lambda r: r.relative)


class BatchProgress:
    """Progress on stderr. On a terminal: one overall line and a line per worker, redrawn in place
    (failures stay above them); otherwise one plain line per scene started and finished. A stream
    that cannot be written (a closed pipe, a full disk) silences it: the batch goes on."""

    def __init__(self, total: int, stream=None, live: bool | None = None, quiet: bool = False):
        self.stream = stream or sys.stderr
        self.live = (self.stream.isatty() if live is None else live) and not quiet
        self.quiet = quiet
        self.total = total
        self.counts = {"done": 0, "skipped": 0, "failed": 0}
        self.workers: dict[str, str] = {}  # worker -> what it is doing
        self.scenes: dict[str, tuple[str, str]] = {}  # worker -> (device, scene)
        self.started_at = time.monotonic()
        self._drawn = 0
        self._drawn_at = 0.0

    def started(self, worker: str, device: str, job: SceneJob) -> None:
        self.scenes[worker] = (device, job.relative)
        self.workers[worker] = f"{device}: {job.relative}: loading"
        if self.live:
            self._draw()
        elif not self.quiet:
            self._log(f"{job.relative}: started on {device}")

    def advanced(self, worker: str, report: tuple[int, int, int]) -> None:
        index, before, after = report
        if worker in self.workers:
            device, scene = self.scenes[worker]
            self.workers[worker] = f"{device}: {scene}: pass {index + 1}, {before:,} -> {after:,}"
        if self.live and time.monotonic() - self._drawn_at > 0.1:
            self._draw()

    def finished(self, worker: str, result: SceneResult) -> None:
        self.counts[result.status] = self.counts.get(result.status, 0) + 1
        self.workers.pop(worker, None)
        line = f"{result.relative}: {_describe(result)}"
        if self.live:
            if result.status == "failed":
                self._write(self._clear_text() + f"nanogs-warp batch: {one_line(line)}\n")
            self._draw()
        elif not self.quiet or result.status == "failed":  # quiet: the failures still, as errors
            self._log(line)

    def close(self) -> None:
        if self.live:
            self._write(self._clear_text())

    def _write(self, text: str) -> None:
        """``text`` to the stream, flushed; on an error the progress stops, the batch does not."""
        if not text:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # EPIPE, ENOSPC, a closed file
            self.live, self.quiet = False, True
            self.stream = open(os.devnull, "w")  # noqa: SIM115 - lives as long as the progress

    def _log(self, text: str) -> None:
        self._write(f"nanogs-warp batch: [{sum(self.counts.values())}/{self.total}] {printable(text)}\n")

    def _draw(self) -> None:
        c = self.counts
        lines = [f"batch: {sum(c.values())}/{self.total} scenes ({c['done']} done, {c['skipped']} skipped, "
                 f"{c['failed']} failed), {time.monotonic() - self.started_at:.0f} s"]  # fmt: skip
        lines += [printable(f"  {name} {status}") for name, status in sorted(self.workers.items())]
        self._write(self._clear_text() + "".join(f"{line[:200]}\033[K\n" for line in lines))
        self._drawn, self._drawn_at = len(lines), time.monotonic()

    def _clear_text(self) -> str:
        """What erases the lines drawn last ("" when none are)."""
        drawn, self._drawn = self._drawn, 0
        return f"\033[{drawn}F\033[J" if drawn else ""


def _unnamed(result: SceneResult, line: str | None) -> str:
    """An error or note of the scene without its file's name in front, where it starts so: the
    scene is named beside it (``failed: bad.ply: bad.ply: not a PLY file`` read twice)."""
    line = line or ""
    for named in (f"{result.input}: ", f"{Path(result.relative).name}: "):
        line = line.removeprefix(named)
    return line


def _describe(result: SceneResult) -> str:
    if result.status == "failed":
        return f"FAILED on {result.device}: {_unnamed(result, result.error)}"
    counts = ", ".join(f"{o['count']:,}" for o in result.outputs)
    if result.status == "skipped":
        return f"skipped (up to date: {counts})"
    return f"{result.input_count:,} -> {counts} splats in {result.seconds:.2f} s on {result.device}"


def format_summary(results: list[SceneResult], seconds: float) -> str:
    """The table printed at the end: scene, count in, counts out, seconds, device, status; then
    one line per failure and the totals."""
    header = ("scene", "in", "out", "seconds", "device", "status")
    rows = [(printable(r.relative), f"{r.input_count:,}" if r.input_count is not None else "-",
             " / ".join(f"{o['count']:,}" for o in r.outputs) or "-",
             f"{r.seconds:.2f}", r.device, r.status) for r in results]  # fmt: skip
    widths = [max(len(h), *(len(row[i]) for row in rows)) if rows else len(h) for i, h in enumerate(header)]
    right = {1, 2, 3}

    def line(cells):
        return "  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths))).rstrip()

    out = [line(header), line(["-" * w for w in widths]), *(line(row) for row in rows)]
    out += [one_line(f"failed: {r.relative}: {_unnamed(r, r.error)}") for r in results if r.status == "failed"]
    out += [one_line(f"note: {r.relative}: {_unnamed(r, note)}") for r in results for note in r.notes]
    totals = {s: sum(r.status == s for r in results) for s in ("done", "skipped", "failed")}
    out.append(f"{len(results)} scenes: {totals['done']} done, {totals['skipped']} skipped, "
               f"{totals['failed']} failed, {seconds:.2f} s")  # fmt: skip
    return "\n".join(out)


def summary_json(results: list[SceneResult], seconds: float, shard: tuple[int, int] = (0, 1)) -> dict:
    totals = {s: sum(r.status == s for r in results) for s in ("done", "skipped", "failed")}
    return {"scenes": [r.to_json() for r in results], **totals, "shard": f"{shard[0]}/{shard[1]}",
            "seconds": round(seconds, 4)}  # fmt: skip


def plan_batch(jobs: list[SceneJob], force: bool) -> list[dict]:
    """``--dry-run``: for each scene what a run would do (``planned``: "run", "skip" or "fail", and
    why) and the outputs it would write; nothing is written."""
    plan = []
    for job in jobs:
        action, reason = planned(job, force)
        plan.append({"input": str(job.input), "relative": job.relative, "action": action, "reason": reason,
                     "outputs": [str(job.output_path(b)) for b in job.budgets]})  # fmt: skip
    return plan


def format_plan(plan: list[dict]) -> str:
    """One line per scene (action, scene, why), then the totals."""
    width = max(len(printable(p["relative"])) for p in plan) if plan else 0
    out = [f"{p['action']:4s}  {printable(p['relative']).ljust(width)}  {printable(p['reason'] or 'up to date')}".rstrip()
           for p in plan]  # fmt: skip
    totals = {a: sum(p["action"] == a for p in plan) for a in ("run", "skip", "fail")}
    out.append(f"{len(plan)} scenes: {totals['run']} to run, {totals['skip']} up to date, {totals['fail']} would fail "
               "(dry run: nothing written)")  # fmt: skip
    return "\n".join(out)
