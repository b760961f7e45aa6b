"""`render_dataset`: plan, skip what is already done, execute, keep the manifest current."""
from __future__ import annotations

import contextlib
import copy
import json
import os
import shlex
import signal
import threading
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import msps_render
from msps_render.dataset import file_digest
from msps_render.dataset.manifest import MANIFEST, SHARD_DIR, new_manifest, read_manifest, write_manifest
from msps_render.errors import InputError, Interrupted, brief
from msps_render.scene.materials import material_pool, pool_difference
from msps_render.config_io import apply_overrides
from msps_render.pipeline.config import (DatasetConfig, _qualify, config_hash, config_json, validate_config)
from msps_render.pipeline.execute import WorkerSettings, run_dask, run_local
from msps_render.pipeline.outdir import (OutLock, check_out_dir, remove_dataset, remove_if_empty,
                                         remove_temporaries, remove_unrecorded)
from msps_render.pipeline.plan import Task, plan
from msps_render.pipeline.validate import validate_inputs
from msps_render.render.variant import env_threads, mitsuba_info, resolve_variant


def _dist_version(name: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return None


def _versions(variant: str) -> dict:
    return {"msps": msps_render.__version__, "mitsuba": mitsuba_info()["mitsuba"], "drjit": _dist_version("drjit"),
            "variant": variant}


# Keys of `versions` a resume must match: shards of one dataset come from one renderer.
RENDERER_KEYS = ("variant", "mitsuba", "drjit")


def renderer_difference(stored: dict, here: dict) -> str | None:
    """None if `here` renders like `stored` (keys the older manifest lacks are not compared), else
    'stored X vs here Y' naming both."""
    keys = [k for k in RENDERER_KEYS if stored.get(k) is not None and stored.get(k) != here.get(k)]
    if not keys:
        return None

    def desc(v: dict) -> str:
        return ", ".join(f"{k} {v.get(k)}" for k in keys)

    return f"rendered with {desc(stored)}, this run would use {desc(here)}"


def pools_of(tasks) -> dict[str, dict[str, str]]:
    """{condition: {material: content digest}}: the measured-material pool each condition draws from
    on this host (`scene.materials.material_pool`)."""
    out: dict[str, dict[str, str]] = {}
    for t in tasks:
        if t.condition not in out:
            out[t.condition] = material_pool(DatasetConfig.model_validate_json(t.config_json).scene.materials)
    return out


def pools_difference(stored: dict, here: dict) -> str | None:
    """None if every condition's pool matches, else the first difference (naming the materials)."""
    for cond in sorted(set(stored) | set(here)):
        why = pool_difference(stored.get(cond, {}), here.get(cond, {}))
        if why:
            return (f"condition {cond}: " if cond else "") + why
    return None


def _flat(d, prefix: str = "") -> dict:
    if not isinstance(d, dict):
        return {prefix: d}
    out = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        out.update(_flat(v, key) if isinstance(v, dict) and v else {key: v})
    return out


_ABSENT = "<absent>"


def config_difference(stored: dict, given: dict, limit: int = 3) -> str:
    """'key: stored X vs given Y' for the first `limit` differing keys ('' when equal)."""
    a, b = _flat(stored), _flat(given)
    keys = sorted(k for k in set(a) | set(b) if a.get(k, _ABSENT) != b.get(k, _ABSENT))
    parts = [f"{k}: stored {json.dumps(a.get(k, _ABSENT))} vs given {json.dumps(b.get(k, _ABSENT))}"
             for k in keys[:limit]]
    return "; ".join(parts) + (f" (and {len(keys) - limit} more keys)" if len(keys) > limit else "")


def _force_deletes(out: Path, n: int) -> str:
    return f"--force deletes the {n} finished shard{'s' if n != 1 else ''} in {out} and starts over"


def resume_config(out: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> DatasetConfig | None:
    """The config to finish the dataset in `out` with: the one stored in its manifest, so that
    `--resume` needs no retyped `--set`.  A `--set` (or --seed) that changes it is refused with one
    line showing the difference.  None when `out` holds no started dataset (render as given)."""
    out = Path(out).expanduser()
    m = read_manifest(out) if (out / MANIFEST).is_file() else None
    if not m or not m.get("shards") or not isinstance(m.get("config"), dict):
        return None
    stored = m["config"]
    source = str(out / MANIFEST)
    cfg = validate_config(apply_overrides(copy.deepcopy(stored), list(overrides), _qualify), source)
    diff = config_difference(stored, json.loads(config_json(cfg)))
    if diff:
        n = len(m["shards"])
        raise InputError(out, f"--resume finishes the stored config and --set changes it ({diff}); drop that "
                              f"--set to resume, or {_force_deletes(out, n)} with the new config")
    cfg._source = source
    return cfg


class _Terminated(BaseException):
    """Raised in the main thread by our SIGTERM handler (like KeyboardInterrupt for SIGINT)."""


def _on_sigterm(signum, frame):
    raise _Terminated()


def render_dataset(cfg: DatasetConfig, out: str | Path, workers: int = 1, scheduler: str | None = None,
                   resume: bool = False, force: bool = False, variant: str | None = None,
                   threads: int | None = None, progress: bool = True, recycle_after: int | None = None,
                   max_tasks_per_child: int | None = None, space_check: bool = True) -> dict:
    """Render (or finish) the dataset `cfg` into `out`. Returns the final manifest.

    Order (docs/reliability.md): validate every input, check `out` (a directory
    we may write, empty or ours), lock it, then write.  SIGINT/SIGTERM stop the
    workers, keep every finished shard in the manifest, delete temporaries and
    raise `Interrupted`; any other failure before the first shard leaves nothing.
    `recycle_after`: replace a local worker after that many shards (None: never).
    `space_check`: refuse (warn when tight) before rendering when the shards will not fit (`space.py`).
    """
    recycle_after = recycle_after if recycle_after is not None else max_tasks_per_child  # old name
    out = Path(out).expanduser().absolute()  # Dask workers resolve relative paths in their own cwd
    mode = "spectral" if getattr(cfg.scene, "mode", "rgb") == "spectral" else "rgb"
    variant = resolve_variant(mode, variant)  # a wrong --variant: one line first, not in a worker
    env_threads()  # a bad MSPS_THREADS too
    validate_inputs(cfg, getattr(cfg, "_source", None))
    tasks = plan(cfg)
    check_out_dir(out, has_manifest=(out / MANIFEST).is_file())
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    with OutLock(out):
        try:
            return _render_locked(RenderJob(cfg=cfg, out=out, tasks=tasks, variant=variant, workers=workers,
                                            scheduler=scheduler, resume=resume, force=force, threads=threads,
                                            progress=progress, recycle_after=recycle_after,
                                            space_check=space_check))
        finally:
            if created:  # still locked: another render cannot have started writing into it yet
                remove_if_empty(out)


def worker_threads(threads: int | None, workers: int) -> int | None:
    """drjit threads per local worker: as given, else `MSPS_THREADS`, else cores / workers.

    Why: with drjit's default (all cores) in every worker, 2 workers run 4 threads on 2 cores;
    measured on the full paper-train corpus, one thread per worker renders it in 254 s instead of
    311 s (docs/benchmarks.md "Full paper corpus").  None = drjit's default (one worker)."""
    if threads or env_threads() or workers <= 1:
        return threads
    return max(1, (os.cpu_count() or 1) // workers)


@dataclass(frozen=True)
class RenderJob:
    """One `render_dataset` call once its inputs are checked and `out` is locked: what to render,
    where, and how (`_render_locked` takes it whole instead of eleven positional values)."""

    cfg: DatasetConfig
    out: Path
    tasks: list[Task]
    variant: str
    workers: int = 1
    scheduler: str | None = None
    resume: bool = False
    force: bool = False
    threads: int | None = None
    progress: bool = True
    recycle_after: int | None = None
    space_check: bool = True  # refuse (warn when tight) when the shards will not fit (`space.py`)


def _render_locked(job: RenderJob) -> dict:
    cfg, out, tasks, variant, workers, scheduler = (job.cfg, job.out, job.tasks, job.variant, job.workers,
                                                    job.scheduler)
    force, threads = job.force, job.threads
    h = config_hash(cfg)
    existing = read_manifest(out)
    versions = _versions(variant)
    pools = pools_of(tasks)
    if existing is not None and existing.get("shards") and not force:  # an empty manifest protects nothing
        n = len(existing["shards"])
        if existing.get("config_hash") != h:
            diff = config_difference(existing.get("config") or {}, json.loads(config_json(cfg)))
            raise InputError(out, f"holds {n} finished shard{'s' if n != 1 else ''} of a different config "
                                  f"({diff or existing.get('config_hash', '?')[:12] + ' != ' + h[:12]}); "
                                  f"`--resume` without --set finishes that dataset, or {_force_deletes(out, n)} "
                                  "with this config")
        if not job.resume:
            raise InputError(out, f"already holds this dataset ({n} of {len(tasks)} shards finished); --resume "
                                  f"finishes it, or {_force_deletes(out, n)}")
        why = renderer_difference(existing.get("versions") or {}, versions)
        if why:
            raise InputError(out, f"--resume refused: its {n} shards were {why}; one dataset must come from one "
                                  f"renderer (--variant {existing['versions'].get('variant')} on the same "
                                  f"Mitsuba), or {_force_deletes(out, n)}")
        if existing.get("material_pool") is not None:
            why = pools_difference(existing["material_pool"], pools)
            if why:
                raise InputError(out, f"--resume refused: the measured materials found here differ from those "
                                      f"its {n} shards drew from ({why}); use the same MSPS_MERL_DIR / brdf/ "
                                      f"files, or {_force_deletes(out, n)}")
    if job.space_check:
        _check_space(cfg, out, tasks, existing, force, h, variant, threads)
    if existing is not None and (force or existing.get("config_hash") != h or not existing.get("shards")):
        remove_dataset(out)  # only the toolkit's own files
        existing = None
    remove_temporaries(out)  # partial shards from a crash
    (out / SHARD_DIR).mkdir(exist_ok=True)
    manifest = existing if existing is not None else new_manifest(
        config_json(cfg), h, cfg.dataset.seed, tasks, versions)
    if existing is None:
        manifest["material_pool"] = pools
    done = {}
    for t in tasks:
        entry = manifest["shards"].get(t.name)
        f = out / SHARD_DIR / t.name
        if entry and f.is_file() and file_digest(f) == entry["file_sha256"]:
            done[t.name] = entry
    manifest["shards"] = {k: v for k, v in manifest["shards"].items() if k in done}
    manifest["complete"] = False
    write_manifest(out, manifest)
    todo = [t for t in tasks if t.name not in done]

    bar = _Progress(len(tasks), len(done), sum(e["n_patches"] for e in done.values()), job.progress)

    def on_done(task, info):
        manifest["shards"][task.name] = info
        write_manifest(out, manifest)
        bar.update(info["n_patches"])

    ws = WorkerSettings(out_dir=str(out), variant=variant, threads=worker_threads(job.threads, workers),
                        material_pool=manifest.get("material_pool"))
    t0 = time.perf_counter()
    main_thread = threading.current_thread() is threading.main_thread()
    old_term = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None
    stopped_by = None
    try:
        if scheduler == "slurm":  # threads as given: the jobs' CPUs decide, not this machine's
            from msps_render.pipeline.slurm import run_slurm

            run_slurm(todo, ws, workers, on_done, cfg.scheduler.slurm, job.threads)
        elif scheduler:
            run_dask(todo, ws, scheduler, workers, on_done)
        else:
            run_local(todo, ws, workers, on_done, recycle_after=job.recycle_after)
    except BaseException as e:
        stopped_by = _stopped_by(e)
        if stopped_by is None:
            with _signals_ignored(main_thread):
                bar.close(ok=False)  # the command ends on its one error line
                _cleanup_failed(out, manifest)
            raise
    finally:
        bar.close()
        if main_thread:
            signal.signal(signal.SIGTERM, old_term)
    if stopped_by is not None:
        with _signals_ignored(main_thread):  # a second Ctrl-C must not interrupt the cleanup
            remove_temporaries(out)
            if not scheduler:  # local workers are dead by now; Dask workers may still be writing
                remove_unrecorded(out, manifest)
            write_manifest(out, manifest)  # every shard finished before the signal
        raise Interrupted(int(stopped_by), len(manifest["shards"]), len(tasks))
    manifest["n_patches"] = sum(e["n_patches"] for e in manifest["shards"].values())
    manifest["n_frames"] = sum(e["n_frames"] for e in manifest["shards"].values())
    manifest["complete"] = len(manifest["shards"]) == len(tasks)
    manifest["last_run"] = {"wall_seconds": time.perf_counter() - t0, "workers": workers,
                            "scheduler": scheduler or "local", "shards_rendered": len(todo)}
    if manifest["complete"] and manifest["n_patches"] == 0:
        why = zero_patch_cause(cfg)
        remove_dataset(out)  # a dataset of 0 patches trains nothing: leave none behind
        remove_if_empty(out / SHARD_DIR)
        raise InputError(out, f"the render yielded 0 patches: {why}; nothing kept")
    write_manifest(out, manifest)
    if manifest["complete"]:
        _write_card(out)
    return manifest


def _check_space(cfg, out: Path, tasks, existing: dict | None, force: bool, h: str, variant: str,
                 threads: int | None) -> None:
    """Refuse before rendering when the shards still to render will not fit under `out` (counting the
    old shards this render deletes first); warn when they take most of the room."""
    import sys

    from msps_render.pipeline.space import check_space, space_line

    keep = existing is not None and not force and existing.get("config_hash") == h
    todo = len(tasks) - (len(existing.get("shards") or {}) if keep else 0)
    reclaim = 0 if keep else sum(p.stat().st_size for p in (out / SHARD_DIR).glob("shard-*.h5"))
    try:
        check = check_space(cfg, tasks, todo, out, variant, threads, reclaim)
    except Exception as e:  # noqa: BLE001 - advice only: a probe that fails (a full /tmp) must not stop the render
        print(f"warning: {out}: free space not checked ({type(e).__name__}: {brief(str(e), 100)})", file=sys.stderr)
        return
    if not check.fits:
        raise InputError(out, f"not enough free space: {space_line(check)}; make room, choose another --out, "
                              "or --no-space-check to render anyway (a full disk then stops it cleanly and "
                              "--resume finishes it)")
    if check.tight:
        print(f"warning: {out}: {space_line(check)}; the disk may fill up before the end", file=sys.stderr)


def zero_patch_cause(cfg: DatasetConfig) -> str:
    """Why frames give no patch: the patch grid against the frame size and the coverage threshold."""
    p, c = cfg.dataset.patches, cfg.scene.camera
    return (f"no {p.size}x{p.size} window (stride {p.stride}) of the {c.width}x{c.height} frames is at least "
            f"{p.min_coverage:.0%} object (dataset.patches.min_coverage); use a smaller dataset.patches.size, "
            "a lower min_coverage or larger scene.camera.width/height")


def patch_grid_warning(cfg: DatasetConfig) -> str | None:
    """A warning before rendering when the patch grid is so coarse for the frame that a render may yield
    few or 0 patches (a window is kept only where the object covers min_coverage of it): patches wider
    than half the shorter frame side.  `msps config show --probe N` counts them on real masks."""
    from msps_render.patches import window_origins

    p, c = cfg.dataset.patches, cfg.scene.camera
    if 2 * p.size <= min(c.width, c.height):
        return None
    n = len(window_origins(c.height, c.width, p.size, p.stride))
    return (f"{p.size}x{p.size} patches in {c.width}x{c.height} frames: only {n} window{'s' if n != 1 else ''} "
            f"per frame, each kept only where the object covers {p.min_coverage:.0%} of it; the render may "
            "yield few or 0 patches (it then fails); `--probe 2` counts them")


def _write_card(out: Path) -> None:
    """DIR/card.png + card.json of the finished dataset.  A failure here costs the card, not the
    render (the dataset is complete and recorded): a warning names `msps card` to retry."""
    import sys

    from msps_render.dataset.card import write_card

    try:
        write_card(out)
    except Exception as e:  # noqa: BLE001 - never fail a finished render over its summary picture
        print(f"warning: dataset card not written ({type(e).__name__}: {e}); retry with "
              f"`msps card {shlex.quote(str(out))}`",
              file=sys.stderr)


def _cleanup_failed(out: Path, manifest: dict) -> None:
    """After an error: no temporaries; with no shard rendered, no manifest and no shards/ either.
    Where the manifest cannot be written (the disk is still full), the one on disk stays (written
    atomically after every shard) and the shards it does not record go: disk == manifest, and the
    error that stopped the render is the one reported."""
    remove_temporaries(out)
    try:
        if manifest["shards"]:
            write_manifest(out, manifest)
        else:
            (out / MANIFEST).unlink(missing_ok=True)
            remove_if_empty(out / SHARD_DIR)
    except OSError:
        manifest = read_manifest(out) or {"shards": {}}
    remove_unrecorded(out, manifest)


@contextlib.contextmanager
def _signals_ignored(main_thread: bool):
    if not main_thread:
        yield
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _stopped_by(e: BaseException):
    """The signal behind an exception (SIGINT, SIGTERM) or None.  Why the chain: a Ctrl-C that lands inside
    `mi.render` reaches us as drjit's RuntimeError ("error while performing a custom operation") with the
    KeyboardInterrupt as its cause, which a plain `except KeyboardInterrupt` missed (a traceback, exit 1)."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, KeyboardInterrupt):
            return signal.SIGINT
        if isinstance(e, _Terminated):
            return signal.SIGTERM
        e = e.__cause__ or e.__context__
    return None


class _Progress:
    """Shards, patches, patches/s and ETA on one line (rich); silent when disabled."""

    def __init__(self, total: int, done: int, patches: int, enabled: bool):
        self.total, self.done, self.patches, self.enabled = total, done, patches, enabled
        self.t0 = time.perf_counter()
        self.new_patches = 0
        self._p = self._lines = None
        if enabled and not sys.stderr.isatty():  # a log file: plain lines at a steady cadence
            from msps_render.progress import LineTicker

            self._lines = LineTicker("render", total, unit="shard", start=done)
        elif enabled:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self._p = Progress(TextColumn("shards {task.completed}/{task.total}"), BarColumn(),
                               TextColumn("{task.fields[patches]} patches, {task.fields[rate]:.0f} patches/s"),
                               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), transient=False)
            self._p.start()
            self._id = self._p.add_task("render", total=total, completed=done, patches=patches, rate=0.0)

    def update(self, n_patches: int) -> None:
        self.done += 1
        self.patches += n_patches
        self.new_patches += n_patches
        rate = self.new_patches / max(time.perf_counter() - self.t0, 1e-9)
        if self._p:
            self._p.update(self._id, completed=self.done, patches=self.patches, rate=rate)
        if self._lines:
            self._lines.note(f"{self.patches} patches, {rate:.0f} patches/s")
            self._lines.update(self.done)

    def close(self, ok: bool = True) -> None:
        if self._lines:
            self._lines.close(ok)
            self._lines = None
        if self._p:
            self._p.stop()
            self._p = None
