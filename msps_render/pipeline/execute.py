"""Execute tasks: render each shard in a worker, write it atomically, record it in the manifest.

`render_shard` is the whole unit of work and a plain function of its task, so
the same code runs in a local `spawn` process pool (Mitsuba is initialised
only inside workers; workers are recycled every N shards to bound JIT/memory
growth) or on a Dask cluster.  Only the parent touches the manifest.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from msps_render.pipeline.config import DatasetConfig
from msps_render.pipeline.manifest import SHARD_DIR
from msps_render.pipeline.plan import Task, frame_rngs, frame_seed


@dataclass(frozen=True)
class WorkerSettings:
    out_dir: str
    variant: str
    threads: int | None = None


def render_shard(task: Task, ws: WorkerSettings) -> dict:
    """Sample, render, patchify and write one shard. Returns its manifest entry."""
    import msps_render
    from msps_render.patches import patchify
    from msps_render.render import render_frame
    from msps_render.scene.sample import sample_scene
    from msps_render.shards import FrameRecord, Patches, ShardContent, write_shard

    cfg = DatasetConfig.model_validate_json(task.config_json)
    d = cfg.dataset
    t0 = time.perf_counter()
    render_s = 0.0
    pats, fidx, frames = [], [], []
    for j, rng in enumerate(frame_rngs(task, d.frames_per_shard)):
        fseed = frame_seed(task, j)
        spec = sample_scene(cfg.scene, rng, seed=fseed, frame_index=task.shard_in_condition * d.frames_per_shard + j)
        tr = time.perf_counter()
        frame = render_frame(spec, variant=ws.variant, threads=ws.threads)
        render_s += time.perf_counter() - tr
        sensor = getattr(cfg.scene, "sensor", None)  # optional sensor model (msps_render.spectral)
        if sensor is not None and getattr(sensor, "enabled", True):
            from msps_render.spectral.sensor import apply_sensor

            frame = apply_sensor(frame, sensor, rng)
        p = patchify(frame, d.patches.size, d.patches.stride, d.patches.min_coverage)
        pats.append(p)
        fidx.append(np.full(len(p), j, np.int32))
        env = spec.environment
        frames.append(FrameRecord(
            scene_json=spec.to_json(indent=None), light_dirs=frame.light_dirs, crosstalk=frame.crosstalk,
            light_rgb=np.array([l.rgb for l in spec.lights]), slant_deg=float(np.mean(
                [l.slant_deg for l in spec.lights if l.slant_deg is not None] or [np.nan])),
            env_ratio=float(env.ratio or 0.0) if env else 0.0,
            env_rotation_deg=float(env.rotation_deg) if env else 0.0, spp=spec.integrator.spp,
            frame_seed=fseed, object=spec.shape.name or spec.shape.kind,
            materials=";".join(m.name for m in spec.materials), condition=task.condition,
            image=frame.image if d.storage.store_frames else None,
            normal=frame.normal if d.storage.store_frames else None,
            mask=frame.mask if d.storage.store_frames else None))
    P = d.patches.size
    cat = Patches(
        image=np.concatenate([p.image for p in pats]) if pats else np.zeros((0, P, P, 3), np.float32),
        normal=np.concatenate([p.normal for p in pats]) if pats else np.zeros((0, P, P, 3), np.float32),
        mask=np.concatenate([p.mask for p in pats]) if pats else np.zeros((0, P, P), np.uint8),
        yx=np.concatenate([p.yx for p in pats]) if pats else np.zeros((0, 2), np.int32))
    import mitsuba as mi

    attrs = {"toolkit_version": msps_render.__version__, "mitsuba_version": mi.__version__,
             "variant": ws.variant, "config_hash": _hash(task.config_json), "seed": task.seed,
             "shard_index": task.index, "condition": task.condition}
    out = Path(ws.out_dir) / SHARD_DIR / task.name
    info = write_shard(out, ShardContent(cat, np.concatenate(fidx) if fidx else np.zeros(0, np.int32), frames,
                                         attrs), d.storage.compression, d.storage.image_dtype,
                       d.storage.normal_dtype)
    info.update(condition=task.condition, render_seconds=render_s, wall_seconds=time.perf_counter() - t0)
    return info


def _hash(s: str) -> str:
    import hashlib

    return hashlib.sha256(s.encode()).hexdigest()


def _worker_init(variant: str, threads: int | None) -> None:
    from msps_render.render.variant import activate

    activate(variant, threads)


OnDone = Callable[[Task, dict], None]


def run_local(tasks: Iterable[Task], ws: WorkerSettings, workers: int, on_done: OnDone,
              max_tasks_per_child: int | None = None) -> None:
    tasks = list(tasks)
    if workers <= 1:  # in-process: simplest to debug, same results
        for t in tasks:
            on_done(t, render_shard(t, ws))
        return
    ctx = mp.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                                initargs=(ws.variant, ws.threads),
                                max_tasks_per_child=max_tasks_per_child) as pool:
        futs = {pool.submit(render_shard, t, ws): t for t in tasks}
        for f in cf.as_completed(futs):
            on_done(futs[f], f.result())


def run_dask(tasks: Iterable[Task], ws: WorkerSettings, scheduler: str, workers: int, on_done: OnDone) -> None:
    """`scheduler`: 'dask-local' (a LocalCluster of `workers` processes) or a 'tcp://host:port' address."""
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        from msps_render.errors import InputError

        raise InputError("--scheduler", "Dask is not installed (pip install 'msps[dask]')") from None
    tasks = list(tasks)
    cluster = None
    if scheduler == "dask-local":
        cluster = LocalCluster(n_workers=max(1, workers), threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        futs = {client.submit(render_shard, t, ws, key=f"msps-{t.name}-{t.config_json.__hash__()}", pure=False): t
                for t in tasks}
        for f in as_completed(list(futs)):
            on_done(futs[f], f.result())
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
