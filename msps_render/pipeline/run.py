"""`render_dataset`: plan, skip what is already done, execute, keep the manifest current."""
from __future__ import annotations

import shutil
import time
from pathlib import Path

from msps_render.errors import InputError
from msps_render.pipeline.config import DatasetConfig, config_hash, config_json
from msps_render.pipeline.execute import WorkerSettings, run_dask, run_local
from msps_render.pipeline.manifest import SHARD_DIR, new_manifest, read_manifest, write_manifest
from msps_render.pipeline.plan import plan
from msps_render.shards import file_digest


def _versions(variant: str) -> dict:
    import mitsuba as mi

    import msps_render

    return {"msps": msps_render.__version__, "mitsuba": mi.__version__, "variant": variant}


def render_dataset(cfg: DatasetConfig, out: str | Path, workers: int = 1, scheduler: str | None = None,
                   resume: bool = False, force: bool = False, variant: str | None = None,
                   threads: int | None = None, progress: bool = True, max_tasks_per_child: int | None = None) -> dict:
    """Render (or finish) the dataset `cfg` into `out`. Returns the final manifest."""
    from msps_render.render.variant import resolve_variant

    out = Path(out)
    h = config_hash(cfg)
    existing = read_manifest(out) if out.is_dir() else None
    if existing is not None:
        if existing.get("config_hash") != h and not force:
            raise InputError(out, "holds a dataset made with a different config "
                                  f"({existing.get('config_hash', '?')[:12]} != {h[:12]}); use --force to replace it")
        if existing.get("config_hash") == h and not (resume or force):
            raise InputError(out, "already holds this dataset; use --resume to finish it or --force to redo it")
    if force and out.is_dir():
        shutil.rmtree(out / SHARD_DIR, ignore_errors=True)
        (out / "dataset.json").unlink(missing_ok=True)
        existing = None
    tasks = plan(cfg)
    mode = "spectral" if getattr(cfg.scene, "mode", "rgb") == "spectral" else "rgb"
    variant = variant or resolve_variant(mode)
    (out / SHARD_DIR).mkdir(parents=True, exist_ok=True)
    for stale in (out / SHARD_DIR).glob(".*.tmp"):  # partial shards from a crash
        stale.unlink()
    manifest = existing if (existing is not None and resume) else new_manifest(
        config_json(cfg), h, cfg.dataset.seed, tasks, _versions(variant))
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

    bar = _Progress(len(tasks), len(done), sum(e["n_patches"] for e in done.values()), progress)

    def on_done(task, info):
        manifest["shards"][task.name] = info
        write_manifest(out, manifest)
        bar.update(info["n_patches"])

    ws = WorkerSettings(out_dir=str(out), variant=variant, threads=threads)
    t0 = time.perf_counter()
    try:
        if scheduler:
            run_dask(todo, ws, scheduler, workers, on_done)
        else:
            run_local(todo, ws, workers, on_done, max_tasks_per_child=max_tasks_per_child)
    finally:
        bar.close()
    manifest["n_patches"] = sum(e["n_patches"] for e in manifest["shards"].values())
    manifest["n_frames"] = sum(e["n_frames"] for e in manifest["shards"].values())
    manifest["complete"] = len(manifest["shards"]) == len(tasks)
    manifest["last_run"] = {"wall_seconds": time.perf_counter() - t0, "workers": workers,
                            "scheduler": scheduler or "local", "shards_rendered": len(todo)}
    write_manifest(out, manifest)
    return manifest


class _Progress:
    """Shards, patches, patches/s and ETA on one line (rich); silent when disabled."""

    def __init__(self, total: int, done: int, patches: int, enabled: bool):
        self.total, self.done, self.patches, self.enabled = total, done, patches, enabled
        self.t0 = time.perf_counter()
        self.new_patches = 0
        self._p = None
        if enabled:
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
        if self._p:
            rate = self.new_patches / max(time.perf_counter() - self.t0, 1e-9)
            self._p.update(self._id, completed=self.done, patches=self.patches, rate=rate)

    def close(self) -> None:
        if self._p:
            self._p.stop()
