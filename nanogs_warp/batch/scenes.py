"""Which scenes a batch holds: a directory, a glob pattern or a manifest -> sorted :class:`SceneJob`s,
each with its own output directory, budgets and options; ``--shard i/n`` picks every n-th of them.

No Warp here: the batch's parent process plans with these, its workers (or Ray tasks) run them.
"""

from __future__ import annotations

import fnmatch
import glob
import json
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

from ..budgets import Budget, parse_budgets
from ..config import SimplifyConfig
from ..errors import InputError
from ..file_identity import file_identity
from ..refinement.config import RefineConfig

RECORD_SUFFIX = ".nanogs.json"
_GLOB_CHARS = set("*?[")
# Per-scene keys of a JSON manifest besides "path" (kebab-case spellings are accepted too): the
# method's settings, a preset to start them from, and what else a scene's outputs depend on.
_CONFIG_KEYS = {"k": int, "prune_opacity": float, "samples": int, "seed": int, "lambda_geo": float, "lambda_app": float,
                "cost": str, "operator": str, "pass_fraction": float, "median_cost_factor": float, "fit_size": bool,
                "fit_geometry": bool, "fit_colour": bool}  # fmt: skip
_OUTPUT_KEYS = {"sh_degree", "refine_steps", "refine_size"}
_SCENE_KEYS = {"path", "ratio", "count", "drop_invalid", "preset", *_CONFIG_KEYS, *_OUTPUT_KEYS}
SCENE_SUFFIXES = (".ply", ".spz", ".sog", ".splat")  # files a directory or glob contributes
OUTPUT_SUFFIXES = {"ply": ".ply", "compressed-ply": ".compressed.ply", "spz": ".spz", "sog": ".sog", "splat": ".splat"}


@dataclass(frozen=True)
class SceneJob:
    """One scene of a batch, everything a worker needs to simplify it (picklable, no Warp)."""

    input: Path  # the .ply file
    relative: str  # its path below the batch's input root, "/"-separated; names the scene
    out_dir: Path  # OUTDIR/<relative's directory>
    budgets: tuple[Budget, ...]
    config: SimplifyConfig
    drop_invalid: bool
    size: int  # bytes; -1 when the file is missing (the scene then fails in its worker)
    output_format: str = "ply"  # a nanogs_warp.io format other than "lod"
    refine_steps: int = 0  # refinement steps per output (0: none)
    refine_size: int = 256  # longest side of refinement's training views
    sh_degree: int | None = None  # the outputs' SH degree (None: the input's)

    @property
    def stem(self) -> str:
        return Path(self.relative).stem

    def output_path(self, budget: Budget) -> Path:
        return self.out_dir / f"{self.stem}_{budget.label}{OUTPUT_SUFFIXES[self.output_format]}"

    @property
    def record_path(self) -> Path:
        return self.out_dir / f"{self.stem}{RECORD_SUFFIX}"

    def options(self) -> dict:
        """What the outputs depend on besides the input's bytes; kept in the scene's record."""
        budgets = [({"ratio": b.ratio, "as_written": b.exact_text} if b.typed_apart else {"ratio": b.ratio})
                   if b.ratio is not None else {"count": b.count} for b in self.budgets]  # fmt: skip
        options = {"budgets": budgets, **vars(self.config), "drop_invalid": self.drop_invalid}
        if self.output_format != "ply":  # records of PLY batches stay as they were
            options["format"] = self.output_format
        if self.refine_steps > 0:
            options.update(refine_steps=self.refine_steps, refine_size=self.refine_size)
        if self.sh_degree is not None:
            options["sh_degree"] = self.sh_degree
        return options


@dataclass(frozen=True)
class SceneDefaults:
    """What a scene takes from the command line where its manifest entry does not say otherwise:
    the method's explicit options (``method_options``, laid over a scene's own ``"preset"``), the
    outputs' SH degree and the refinement."""

    method_options: tuple[tuple[str, object], ...] = ()
    sh_degree: int | None = None
    refine_steps: int = 0
    refine_size: int = 256


def find_scenes(
    input: str,
    out_dir: Path,
    budgets: list[Budget] | None,
    config: SimplifyConfig,
    drop_invalid: bool,
    output_format: str = "ply",
    defaults: SceneDefaults = SceneDefaults(),
) -> list[SceneJob]:
    """The batch's scenes sorted by relative path. ``input`` is a directory (every scene file below
    it: ``.ply``, ``.spz``, ``.sog``, ``.splat``; leaving out ``out_dir`` if it lies inside), a glob
    pattern (``**`` recurses), a single scene file, or a manifest: one path per line (``#`` starts a comment line) or a JSON list
    of paths or ``{"path": ..., "ratio"/"count"/<simplify option>: ...}`` objects. Relative
    manifest paths start at the manifest's directory. Outputs go to ``out_dir/<relative>``, where
    ``relative`` is the path below the root: the directory, the pattern's fixed leading directories,
    or the deepest directory that holds every scene of a manifest. A scene's ``config`` is
    ``config``, or ``defaults.method_options`` over its own ``"preset"``; its own settings go over
    either."""
    path = Path(input)
    out_dir = Path(out_dir)
    if path.is_dir():
        if _same_folder(path, out_dir):
            raise InputError(f"the output directory {out_dir} is the input directory; choose another one")
        root, entries = path, [(p, {}) for p in _walk_ply(path, skip=out_dir)]
        what = f"no .ply files under {path} (nor .spz, .sog or .splat files)"
    elif path.is_file() and path.suffix.lower() in SCENE_SUFFIXES:
        root, entries, what = path.parent, [(path, {})], ""
    elif path.is_file():
        entries = _read_manifest(path)
        root = _common_directory([p for p, _ in entries]) if entries else path.parent
        what = f"{path.name}: the manifest lists no scenes"
    elif _GLOB_CHARS & set(input):
        root = _glob_root(input)
        entries = [(Path(p), {}) for p in _glob(input) if _is_scene(p) and Path(p).is_file() and not _inside(Path(p), out_dir)]
        what = f"no .ply files match {input!r} (nor .spz, .sog or .splat files)"
    else:
        raise InputError(f"{input}: no such file, directory or glob pattern")
    if not entries:
        raise InputError(what)

    jobs = [_make_job(p, overrides, root, out_dir, budgets, config, drop_invalid, output_format, defaults)
            for p, overrides in entries]  # fmt: skip
    jobs.sort(key=lambda j: j.relative)
    _check_unique(jobs)
    return jobs


def parse_shard(text: str | None) -> tuple[int, int]:
    """``i/n`` with 0 <= i < n (0-based, as Slurm's ``$SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT``
    when the array starts at 0); None means the whole batch, ``0/1``."""
    if text is None:
        return 0, 1
    parts = text.strip().split("/")
    try:
        i, n = (int(p) for p in parts) if len(parts) == 2 else (None, None)
    except ValueError:
        i, n = None, None
    if i is None or n < 1 or not 0 <= i < n:
        raise InputError(f"--shard {text!r}: expected i/n with 0 <= i < n, e.g. 0/4")
    return i, n


def select_shard(jobs: list[SceneJob], index: int, count: int) -> list[SceneJob]:
    """Scene ``k`` of the sorted list belongs to shard ``k mod count``."""
    return [job for k, job in enumerate(jobs) if k % count == index]


# The default --scene-timeout: a fixed part for starting Warp and compiling its kernels on a fresh
# machine, plus a part per MB of input, larger on the CPU. Both are far above the measured times (a
# 2-core CPU: about 0.03 s per MB all told; an H100: about 0.003 s per MB), so that only a scene
# that would never end reaches them.
TIMEOUT_BASE_S = 300.0
TIMEOUT_PER_MB_S = {"cpu": 0.5, "gpu": 0.1}


def scene_timeout(job: SceneJob, on_gpu: bool, seconds: float | None = None) -> float | None:
    """How long ``job`` may take on one worker: ``seconds`` when given (0: no limit, None), else
    TIMEOUT_BASE_S plus TIMEOUT_PER_MB_S per MB of input."""
    if seconds is not None:
        return seconds if seconds > 0 else None
    return TIMEOUT_BASE_S + TIMEOUT_PER_MB_S["gpu" if on_gpu else "cpu"] * max(job.size, 0) / 1e6


def timed_out_error(limit: float, what: str) -> str:
    """A scene's error past its time limit of ``limit`` seconds: whole seconds from 10 s on, three
    digits below (a 0.5 s limit is not "0 s")."""
    shown = f"{limit:.0f}" if limit >= 10 else f"{limit:.3g}"
    return f"timed out after {shown} s (--scene-timeout); {what}"


def largest_first(jobs: list[SceneJob]) -> list[SceneJob]:
    """The order in which workers take scenes: biggest file first (ties by name), so that one
    large scene does not start last and hold up the end of the batch."""
    return sorted(jobs, key=lambda j: (-j.size, j.relative))


# ----------------------------------------------------------------------------------------------


def _walk_ply(root: Path, skip: Path | None = None) -> list[Path]:
    """The scene files below ``root`` (hidden files and folders left out), leaving out the folder
    ``skip`` (the output folder) however it is reached."""
    skip_ids = {file_identity(skip)} - {None} if skip is not None else set()
    found = []
    for directory, subdirs, files in os.walk(root):
        subdirs[:] = sorted(d for d in subdirs if not d.startswith(".") and file_identity(Path(directory) / d) not in skip_ids)
        found += [Path(directory) / f for f in files if _is_scene(f) and not f.startswith(".")]
    return found


def _same_folder(a: Path, b: Path) -> bool:
    """Whether two paths name the same existing folder, by identity (``file_identity``)."""
    identity = file_identity(a)
    return identity is not None and identity == file_identity(b)


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` lies inside ``folder`` (by the identity of each of its resolved parents)."""
    identity = file_identity(folder)
    return identity is not None and any(file_identity(parent) == identity for parent in Path(os.path.realpath(path)).parents)


def scenes_left_out(input: str, out_dir: Path, jobs: list[SceneJob]) -> list[Path]:
    """The scene files of a folder ``input`` that the batch leaves out because they lie inside the
    output folder ``out_dir`` (which is inside ``input``), other than the batch's own outputs: a
    folder of outputs inside the input is skipped, so that its outputs are never read as scenes,
    and with it whatever else is there."""
    path = Path(input)
    if not path.is_dir() or not out_dir.is_dir() or not _inside(out_dir, path):
        return []
    own = {os.path.realpath(p) for job in jobs for p in (job.record_path, *(job.output_path(b) for b in job.budgets))}
    return [p for p in _walk_ply(out_dir) if os.path.realpath(p) not in own]


def _is_scene(name: str) -> bool:
    return name.lower().endswith(SCENE_SUFFIXES)


def _glob(pattern: str) -> list[str]:
    """The files matching ``pattern``; ``**`` matches any number of folders, found by walking the
    tree without following links to folders (Python's glob follows them, and a link loop made it
    run for ever), each path's folders matched one by one as glob does."""
    if "**" not in pattern:
        return glob.glob(pattern)
    root = _glob_root(pattern)
    parts = Path(pattern).parts[len(root.parts) if str(root) != "." else 0 :]
    pieces = ["(?:[^/]+/)*" if part == "**" else _part_regex(part) + "/" for part in parts]
    if parts and parts[-1] == "**":  # "dir/**": every file below
        pieces[-1] = "(?:[^/]+/)*[^/]+/"
    regex = re.compile("".join(pieces)[:-1] + r"\Z")
    found = []
    for directory, subdirs, files in os.walk(root):  # links to folders are not followed
        subdirs[:] = sorted(d for d in subdirs if not d.startswith("."))
        relative = os.path.relpath(directory, root)
        prefix = "" if relative == "." else relative.replace(os.sep, "/") + "/"
        found += [os.path.join(directory, f) for f in sorted(files) if not f.startswith(".") and regex.match(prefix + f)]
    return found


def _part_regex(part: str) -> str:
    """One path component of a glob pattern (``*``, ``?``, ``[...]``) as a regular expression that
    stays within the component."""
    out, i = [], 0
    while i < len(part):
        c = part[i]
        close = part.find("]", i + 2 if part[i + 1 : i + 2] in ("!", "^") else i + 1) if c == "[" else -1
        if c == "*":
            out.append("[^/]*")
        elif c == "?":
            out.append("[^/]")
        elif close > i:
            body = part[i + 1 : close]
            out.append("[" + ("^" + body[1:] if body[:1] in ("!", "^") else body).replace("\\", "\\\\") + "]")
            i = close
        else:
            out.append(re.escape(c))
        i += 1
    return "".join(out)


def _glob_root(pattern: str) -> Path:
    """The leading directories of ``pattern`` that hold no glob characters."""
    fixed = []
    for part in Path(pattern).parts[:-1]:
        if _GLOB_CHARS & set(part):
            break
        fixed.append(part)
    return Path(*fixed) if fixed else Path(".")


def _common_directory(paths: list[Path]) -> Path:
    return Path(os.path.commonpath([os.path.dirname(os.path.abspath(p)) for p in paths]))


def _read_manifest(path: Path) -> list[tuple[Path, dict]]:
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (some editors write one) is not a name
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path.name}: cannot read the manifest: {e}") from None
    base = Path(os.path.abspath(path)).parent
    if path.suffix.lower() == ".json" or text.lstrip().startswith("["):
        try:
            items = json.loads(text)
        except ValueError as e:  # not JSON, or an integer too long to read
            raise InputError(f"{path.name}: not valid JSON: {e}") from None
        except RecursionError:
            raise InputError(f"{path.name}: nested too deeply to be a list of scenes") from None
        if not isinstance(items, list):
            raise InputError(f"{path.name}: expected a JSON list of paths or {{\"path\": ...}} objects")
        return [_manifest_entry(item, i, path.name, base) for i, item in enumerate(items)]
    lines = [line.strip() for line in text.splitlines()]
    for i, line in enumerate(lines):
        if "\0" in line:
            raise InputError(f"{path.name}: line {i + 1}: a path with a NUL character")
    return [(base / line, {}) for line in lines if line and not line.startswith("#")]


def _manifest_entry(item, i: int, name: str, base: Path) -> tuple[Path, dict]:
    where = f"{name}: entry {i + 1}"
    if isinstance(item, str):
        item = {"path": item}
    if not isinstance(item, dict) or not isinstance(item.get("path"), str) or not item["path"]:
        raise InputError(f"{where}: expected a path or an object with a \"path\" string")
    if "\0" in item["path"]:
        raise InputError(f"{where}: a path with a NUL character")
    options = {key.replace("-", "_"): value for key, value in item.items()}
    unknown = sorted(set(options) - _SCENE_KEYS)
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(_SCENE_KEYS))}")
    return base / options.pop("path"), options


def _make_job(path, overrides, root, out_dir, budgets, config, drop_invalid, output_format, defaults) -> SceneJob:
    relative = Path(os.path.relpath(os.path.abspath(path), os.path.abspath(root)))
    where = relative.as_posix()
    scene_budgets = budgets
    if "ratio" in overrides or "count" in overrides:
        try:
            scene_budgets = parse_budgets(_budget_text(overrides.get("ratio")), _budget_text(overrides.get("count")))
        except InputError as e:
            raise InputError(f"{where}: {e}") from None
    if scene_budgets is None:
        raise InputError(f"{where}: no budget: give --ratio or --count (or per-scene \"ratio\"/\"count\" in a JSON manifest)")
    try:
        scene_config = _scene_config(overrides, config, defaults, where)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    drop = _typed(overrides["drop_invalid"], bool, f"{where}: drop_invalid") if "drop_invalid" in overrides else drop_invalid
    try:
        size = path.stat().st_size
    except OSError:
        size = -1
    job = SceneJob(path, relative.as_posix(), out_dir / relative.parent, tuple(scene_budgets), scene_config, drop, size,
                   output_format, defaults.refine_steps, defaults.refine_size, defaults.sh_degree)  # fmt: skip
    try:
        return replace(job, **_output_settings(overrides, job))
    except InputError as e:
        raise InputError(f"{where}: {e}") from None


def _scene_config(overrides: dict, config: SimplifyConfig, defaults: SceneDefaults, where: str) -> SimplifyConfig:
    """The scene's method settings: its own keys over ``config``, or over its ``"preset"`` with the
    command line's explicit options."""
    if "preset" in overrides:
        config = SimplifyConfig.preset(_typed(overrides["preset"], str, "preset"), **dict(defaults.method_options))
    changes = {key: _typed(overrides[key], kind, key) for key, kind in _CONFIG_KEYS.items() if key in overrides}
    config = replace(config, **changes)
    config.validate()
    return config


def _output_settings(overrides: dict, job: SceneJob) -> dict:
    """The scene's own ``sh_degree`` (0-3, or null for the input's), ``refine_steps`` (0: none) and
    ``refine_size``, checked."""
    changes = {}
    if "sh_degree" in overrides:
        degree = overrides["sh_degree"]
        if degree is not None and (_typed(degree, int, "sh_degree") not in (0, 1, 2, 3)):
            raise InputError(f"sh_degree must be 0, 1, 2, 3 or null, got {degree!r}")
        changes["sh_degree"] = degree
    for key in ("refine_steps", "refine_size"):
        if key in overrides:
            changes[key] = _typed(overrides[key], int, key)
    steps, size = changes.get("refine_steps", job.refine_steps), changes.get("refine_size", job.refine_size)
    if steps or "refine_size" in changes:
        try:
            RefineConfig(steps=steps, size=size).validate()
        except InputError as e:  # its message names the command line's options
            raise InputError(str(e).replace("--refine-steps", "refine_steps").replace("--refine-size", "refine_size")) from None
    return changes


def _budget_text(value) -> str | None:
    """A JSON budget: a number, a list of numbers or the command line's "0.1,0.01" (the caller
    names the scene in an error)."""
    if value is None or isinstance(value, str):
        return value
    values = value if isinstance(value, list) else [value]
    if not values or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        raise InputError('a budget must be a number, a list of numbers or a string like "0.1,0.01"')
    return ",".join(repr(v) for v in values)


def _typed(value, kind, where: str):
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise InputError(f"{where}: expected {kind.__name__}, got {value!r}")
    return value


def _check_unique(jobs: list[SceneJob]) -> None:
    """No two scenes write the same outputs, and no scene's output or record is a scene of the
    batch (an output tree that overlaps the input tree would replace an input)."""
    seen: dict[Path, str] = {}
    for job in jobs:
        key = Path(os.path.realpath(job.record_path))  # never raises, even on a symlink loop
        if key in seen:
            raise InputError(f"{seen[key]} and {job.relative} would write the same outputs ({job.out_dir / job.stem}_*)")
        seen[key] = job.relative
    inputs = {os.path.realpath(job.input): job.relative for job in jobs}
    identities = {file_identity(job.input): job.relative for job in jobs}  # the same file by another path (a folder mounted twice)
    identities.pop(None, None)
    for job in jobs:
        for path in (job.record_path, *(job.output_path(b) for b in job.budgets)):
            scene = inputs.get(os.path.realpath(path)) or identities.get(file_identity(path))
            if scene is not None:
                raise InputError(f"{job.relative}'s output {path} is the scene {scene} of this batch; "
                                 "choose an output folder outside the scenes")  # fmt: skip
