"""Execute tasks: render each shard in a worker, write it atomically, record it in the manifest.

`render_shard` is the whole unit of work and a plain function of its task, so
the same code runs in this process (`--workers 1`), in `WorkerPool` (our own
small `spawn` pool: Mitsuba is initialised only inside workers, workers can be
recycled every N shards, and they die with the driver) or on a Dask cluster.
Only the parent touches the manifest.
"""
from __future__ import annotations

import asyncio
import multiprocessing as mp
import os
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

import msps_render
from msps_render.dataset import FrameRecord, Patches, ShardContent, write_shard
from msps_render.dataset.manifest import SHARD_DIR
from msps_render.errors import InputError, WorkerDied
from msps_render.patches import patchify
from msps_render.pipeline.config import DatasetConfig
from msps_render.pipeline.plan import Task, frame_rngs, frame_seed, sensor_rng
from msps_render.render import render_frame
from msps_render.render.memory import frame_budget, kernel_cache_misses, release_frame_memory
from msps_render.render.pool import ScenePool
from msps_render.render.sensor import apply_sensor
from msps_render.render.shadows import render_shadows
from msps_render.render.variant import activate, flush_denormals, mitsuba_info
from msps_render.scene.sample import sample_scene
from msps_render.scene.spec import SceneSpec
from msps_render.timing import StageTimer, stage


@dataclass(frozen=True)
class WorkerSettings:
    out_dir: str
    variant: str
    threads: int | None = None
    material_pool: dict | None = None  # {condition: {material: digest}} the manifest records (None: unchecked)


def check_material_pool(task: Task, ws: WorkerSettings, cfg: DatasetConfig) -> None:
    """Stop before rendering when this worker's host would draw from another measured-material pool
    than the dataset records (other MERL files, other built-in fits): shards would silently differ."""
    if ws.material_pool is None:
        return
    from msps_render.scene.materials import material_pool, pool_difference

    why = pool_difference(ws.material_pool.get(task.condition, {}), material_pool(cfg.scene.materials))
    if why:
        import socket

        raise InputError(f"{task.name} on {socket.gethostname()}",
                         f"this worker sees other measured materials than the dataset records ({why}); "
                         "give every worker the same MSPS_MERL_DIR / brdf/ files")


def render_shard(task: Task, ws: WorkerSettings, timer: StageTimer | None = None,
                 scenes: ScenePool | None = None) -> dict:
    """Sample, render, patchify and write one shard. Returns its manifest entry.

    `timer` (optional) times every step frame by frame (benchmarks/bench_breakdown.py);
    the shard's write is shared out evenly over its frames.  `scenes`: the worker's pool of
    loaded scenes, kept across its shards (None: a pool for this shard alone); frames do not
    depend on it (render/pool.py).
    """
    flush_denormals()  # a shard's numpy and kernels in one floating-point mode, wherever a run starts
    scenes = scenes if scenes is not None else ScenePool()
    cfg = DatasetConfig.model_validate_json(task.config_json)
    check_material_pool(task, ws, cfg)
    d = cfg.dataset
    t0 = time.perf_counter()
    render_s = 0.0
    pats, fidx, frames = [], [], []
    misses0 = kernel_cache_misses()
    for j, fseed, spec, frame, seconds in _rendered(task, cfg, ws, timer, scenes):
        render_s += seconds
        if d.storage.store_shadows:  # per-light shadow codes, ground truth (render/shadows.py)
            with stage(timer, "shadows"):
                frame = replace(frame, shadow=render_shadows(spec, ws.variant, ws.threads))
        sensor = cfg.sensor  # optional sensor model (render/sensor.py), its own noise stream
        if sensor is not None and sensor.enabled:
            with stage(timer, "sensor"):
                frame = apply_sensor(frame, sensor, sensor_rng(task, j))
        with stage(timer, "patchify"):
            # cut in the stored dtypes: a shard's patches are held at 2 bytes a value until it is written
            p = patchify(frame, d.patches.size, d.patches.stride, d.patches.min_coverage,
                         d.storage.image_dtype, d.storage.normal_dtype)
        pats.append(p)
        fidx.append(np.full(len(p), j, np.int32))
        with stage(timer, "release memory"):
            budget = frame_budget(len(spec.lights))  # flat worker memory, kernels kept for the next scene (docs/benchmarks.md)
            scenes.trim(budget.scenes)
            release_frame_memory(misses0, budget)
            misses0 = kernel_cache_misses()
        env = spec.environment
        with stage(timer, "frame record"):
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
                mask=frame.mask if d.storage.store_frames else None,
                albedo=frame.albedo if d.storage.store_frames else None,
                blend=frame.blend if d.storage.store_frames else None,
                per_light=frame.per_light if d.storage.store_per_light else None,
                env_image=frame.env_image if d.storage.store_per_light else None,
                **rig_record(frame, d.storage.store_frames)))
        if timer is not None:
            timer.end_frame()
    P = d.patches.size
    clock = timer.clock if timer is not None else time.perf_counter
    tw = clock()
    cat = Patches.concat(pats, P)
    pats.clear()  # the per-frame pieces, freed before the shard is written (a second copy at N images each)
    attrs = {"toolkit_version": msps_render.__version__, "mitsuba_version": mitsuba_info()["mitsuba"],
             "variant": ws.variant, "config_hash": _hash(task.config_json), "seed": task.seed,
             "shard_index": task.index, "condition": task.condition}
    out = Path(ws.out_dir) / SHARD_DIR / task.name
    info = write_shard(out, ShardContent(cat, np.concatenate(fidx) if fidx else np.zeros(0, np.int32), frames,
                                         attrs), d.storage.compression, d.storage.image_dtype,
                       d.storage.normal_dtype)
    if timer is not None and frames:
        share = (clock() - tw) / len(frames)
        for f in timer.frames[-len(frames):]:
            f["write"] = f.get("write", 0.0) + share
    info.update(condition=task.condition, render_seconds=render_s, wall_seconds=time.perf_counter() - t0,
                bytes=out.stat().st_size)  # lets status commands spot a truncated shard without hashing it
    return info


def _rendered(task: Task, cfg: DatasetConfig, ws: WorkerSettings, timer: StageTimer | None, scenes: ScenePool):
    """(j, frame seed, spec, frame, render seconds) of each frame of the shard, in order.

    Frames are sampled a launch's group at a time (`render.batch.launch_groups`: `dataset.batch_frames`,
    capped by the memory budget for many lights); a group that can share one kernel launch
    (`render.batch.batchable`) is rendered by `render_batch`, any other frame alone.  With a timer,
    a batch's stage times are shared out evenly over its frames (a frame's row stays its cost)."""
    d = cfg.dataset
    rngs = list(frame_rngs(task, d.frames_per_shard))
    sampled: dict[int, tuple] = {}

    def spec_of(j: int) -> SceneSpec:
        if j not in sampled:
            fseed = frame_seed(task, j)
            with stage(timer, "sample"):
                sampled[j] = (fseed, sample_scene(cfg.scene, rngs[j], seed=fseed,
                                                  frame_index=task.shard_in_condition * d.frames_per_shard + j))
        return sampled[j][1]

    if d.batch_frames > 1:
        from msps_render.render.batch import launch_groups

        groups = _ahead(launch_groups(len(rngs), d.batch_frames, spec_of),
                        lambda g: _prepare([spec_of(j) for j in g], ws, scenes))
    else:
        groups = (range(j, j + 1) for j in range(len(rngs)))
    for g in groups:
        group = []
        for j in g:
            spec = spec_of(j)
            group.append((j, sampled.pop(j)[0], spec))
        yield from _render_group(group, d.storage.store_per_light, ws, timer, scenes)


def _ahead(groups: Iterator[range], prepare: Callable[[range], None]) -> Iterator[range]:
    """`groups` as they come, but each next group is drawn (and `prepare`d) before the current one is
    handed out, so its preparation runs while the current group renders."""
    nxt = next(groups, None)
    while nxt is not None:
        cur, nxt = nxt, next(groups, None)
        if nxt is not None:
            prepare(nxt)
        yield cur


def _batch_scenes(specs: list[SceneSpec], ws: WorkerSettings, scenes: ScenePool):
    """The worker's `render.batch.BatchScenes` (kept with its pooled scenes, across its shards) when these
    frames can share a launch (`render.batch.batchable`), else None."""
    from msps_render.render.batch import BatchScenes, batchable

    if not batchable(specs, activate(ws.variant, ws.threads)):
        return None
    if scenes.batches is None:
        scenes.batches = BatchScenes()
    return scenes.batches


def _prepare(specs: list[SceneSpec], ws: WorkerSettings, scenes: ScenePool) -> None:
    """Start building the shapes of a coming batch in a thread (`render.batch.BatchScenes.prepare`)."""
    batches = _batch_scenes(specs, ws, scenes)
    if batches is not None:
        batches.prepare(specs)


def _render_group(group: list, per_light: bool, ws: WorkerSettings, timer: StageTimer | None, scenes: ScenePool):
    """One launch's frames [(j, frame seed, spec)]: together (`render.batch.render_batch`) when they can
    share it, else one at a time.  Yields what `_rendered` yields."""
    specs = [s for _, _, s in group]
    if len(specs) > 1:
        from msps_render.render.batch import render_batch

        batches = _batch_scenes(specs, ws, scenes)
        if batches is not None:
            before = dict(timer.current) if timer is not None else None
            tr = time.perf_counter()
            out = render_batch(specs, variant=ws.variant, threads=ws.threads, timer=timer, per_light=per_light,
                               scenes=batches)
            share = (time.perf_counter() - tr) / len(specs)
            rest = _share_stages(timer, before, len(specs))
            for n, ((j, fseed, spec), frame) in enumerate(zip(group, out)):
                if n and timer is not None:
                    for k, v in rest.items():
                        timer.add(k, v)
                yield j, fseed, spec, frame, share
            return
    for j, fseed, spec in group:
        tr = time.perf_counter()
        frame = render_frame(spec, variant=ws.variant, threads=ws.threads, timer=timer, per_light=per_light,
                             scenes=scenes)
        yield j, fseed, spec, frame, time.perf_counter() - tr


def _share_stages(timer: StageTimer | None, before: dict | None, n: int) -> dict:
    """Keep 1/n of the stage seconds added since `before` in the current frame; return the share
    each of the other n - 1 frames gets."""
    if timer is None:
        return {}
    added = {k: v - before.get(k, 0.0) for k, v in timer.current.items() if v - before.get(k, 0.0) > 0}
    for k, v in added.items():
        timer.current[k] -= v - v / n
    return {k: v / n for k, v in added.items()}


def rig_record(frame, store_frames: bool) -> dict:
    """The FrameRecord fields of a rig frame (format 2): true and nominal lights, whole-frame shots."""
    spec = frame.spec
    if spec.rig is None:
        return {}
    from msps_render.rig import nominal_rig_of_spec

    true, nominal = frame.rig, nominal_rig_of_spec(spec)
    pos = true.positions if true.positions is not None else np.full((true.n_lights, 3), np.nan)
    return {"rig_json": spec.rig.model_dump_json(), "light_pos": pos, "nominal_dirs": nominal.light_dirs,
            "nominal_crosstalk": nominal.crosstalk,
            "shots": frame.shots if store_frames else None, "points": frame.points if store_frames else None,
            "shadow": frame.shadow if store_frames else None}


def _hash(s: str) -> str:
    import hashlib

    return hashlib.sha256(s.encode()).hexdigest()


def _worker_init(variant: str, threads: int | None) -> None:
    activate(variant, threads)


OnDone = Callable[[Task, dict], None]


def run_local(tasks: Iterable[Task], ws: WorkerSettings, workers: int, on_done: OnDone,
              recycle_after: int | None = None) -> None:
    """Render `tasks` in this process (`workers <= 1`) or in a `WorkerPool` of `workers` processes."""
    tasks = list(tasks)
    if workers <= 1:  # in-process: simplest to debug, same results
        scenes = ScenePool()
        for t in tasks:
            on_done(t, render_shard(t, ws, scenes=scenes))
        return
    pool = WorkerPool(min(workers, len(tasks)) or 1, ws.variant, ws.threads, recycle_after)
    try:
        pool.run(tasks, ws, on_done)
    except BaseException:  # error, Ctrl-C, SIGTERM: stop every worker now, keep what already finished
        pool.kill()
        pool.drain(on_done)
        raise
    finally:
        pool.close()


# ------------------------------------------------------------------ the local worker pool
class RemoteTraceback(Exception):
    """Carries a worker's formatted traceback as the `__cause__` of the re-raised error."""

    def __init__(self, tb: str):
        super().__init__(tb)
        self.tb = tb

    def __str__(self) -> str:
        return f"\n\"\"\"\n{self.tb}\"\"\""


def _portable(exc: BaseException) -> tuple[BaseException, str]:
    """(exception that survives pickling, worker traceback text)."""
    import pickle
    import traceback

    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    try:
        pickle.loads(pickle.dumps(exc))
        return exc, tb
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}"), tb


def _die_with_parent(lifeline, parent_pid: int) -> None:
    """Make this worker exit within a second of the driver's death, however it dies.

    Linux: PR_SET_PDEATHSIG delivers SIGKILL when the parent goes (even on its
    SIGKILL).  Everywhere: a daemon thread blocks on the read end of a pipe whose
    only write end the parent holds; the kernel closes it when the parent dies,
    the read returns EOF, and the thread ends the process.  The getppid check
    covers a parent that died before either was armed.
    """
    import threading

    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
        except Exception:  # pragma: no cover - no libc / seccomp: the pipe still works
            pass
    if os.getppid() != parent_pid:
        os._exit(3)

    def watch():
        try:
            lifeline.recv()
        except BaseException:
            pass
        os._exit(3)

    threading.Thread(target=watch, name="msps-lifeline", daemon=True).start()


def _worker_main(conn, lifeline, parent_pid: int, variant: str, threads: int | None) -> None:
    """Worker loop: receive (task, settings), render, send ('ok', name, info) or ('error', name, exc, tb).

    SIGINT is ignored (Ctrl-C reaches the whole process group; the driver decides
    and stops workers itself); SIGTERM keeps its default (exit).
    """
    _die_with_parent(lifeline, parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        _worker_init(variant, threads)
    except BaseException as e:
        conn.send(("error", None, *_portable(e)))
        return
    scenes = ScenePool()  # loaded scenes kept across this worker's shards
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            os._exit(3)
        if msg is None:  # asked to retire
            break
        task, ws = msg
        try:
            info = render_shard(task, ws, scenes=scenes)
        except BaseException as e:
            conn.send(("error", task.name, *_portable(e)))
            continue
        conn.send(("ok", task.name, info))
    conn.close()


class _Worker:
    def __init__(self, ctx, variant: str, threads: int | None):
        self.conn, child_conn = ctx.Pipe(duplex=True)
        life_r, self.lifeline = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_worker_main, name="msps-worker", daemon=True,
                                args=(child_conn, life_r, os.getpid(), variant, threads))
        self.proc.start()
        child_conn.close()
        life_r.close()
        self.task: Task | None = None
        self.done = 0

    def send(self, task: Task, ws: WorkerSettings) -> None:
        self.task = task
        self.conn.send((task, ws))

    def stop(self, timeout: float = 10.0) -> None:
        """Graceful: ask to exit after the current task, wait, then kill."""
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.proc.join(timeout)
        self.kill()
        self.close()

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(5)

    def close(self) -> None:
        for c in (self.conn, self.lifeline):
            try:
                c.close()
            except OSError:
                pass


class WorkerPool:
    """A small process pool for shards: `spawn` workers, optional recycling, no orphans.

    Why not `concurrent.futures.ProcessPoolExecutor`: with `max_tasks_per_child`
    it deadlocks once workers reach their limit (CPython gh-115634, 3.11+), a
    worker killed mid-task breaks the whole pool, and its workers outlive a
    SIGKILLed driver.  Here the parent owns everything: it hands out one task at
    a time per worker over a pipe, retires a worker after `recycle_after` shards
    (asks it to exit, joins it, spawns a fresh one), and every worker dies with
    the parent (`_die_with_parent`).  Only the parent touches the manifest.
    """

    def __init__(self, n_workers: int, variant: str, threads: int | None = None,
                 recycle_after: int | None = None):
        self.ctx = mp.get_context("spawn")
        self.n = max(1, int(n_workers))
        self.variant, self.threads = variant, threads
        self.recycle_after = int(recycle_after) if recycle_after else None
        self.workers: list[_Worker] = []
        self.spawned = 0  # workers started over the pool's life (recycling adds some)

    def _spawn(self) -> _Worker:
        w = _Worker(self.ctx, self.variant, self.threads)
        self.spawned += 1
        self.workers.append(w)
        return w

    def _retire(self, w: _Worker) -> None:
        self.workers.remove(w)
        w.stop()

    def run(self, tasks: Iterable[Task], ws: WorkerSettings, on_done: OnDone) -> None:
        from multiprocessing.connection import wait

        pending = deque(tasks)
        while len(self.workers) < min(self.n, len(pending)):
            self._spawn()
        for w in list(self.workers):
            if pending:
                w.send(pending.popleft(), ws)
        while any(w.task is not None for w in self.workers):
            busy = [w for w in self.workers if w.task is not None]
            ready = wait([w.conn for w in busy] + [w.proc.sentinel for w in busy], timeout=0.5)
            for w in busy:
                if w.conn not in ready and w.proc.sentinel not in ready:
                    continue
                msg = None
                try:
                    if w.conn.poll():
                        msg = w.conn.recv()
                except (EOFError, OSError):
                    msg = None
                if msg is None:
                    if w.proc.is_alive() and w.proc.sentinel not in ready:
                        continue
                    w.proc.join(1)
                    code = w.proc.exitcode
                    how = (f"signal {signal.Signals(-code).name}" if code is not None and code < 0
                           else f"exit code {code}")
                    raise WorkerDied(f"a worker process (pid {w.proc.pid}) died ({how}) while rendering "
                                     f"{w.task.name if w.task else 'a shard'}; rerun with --resume")
                kind, name, *rest = msg
                if kind == "error":
                    exc, tb = rest
                    exc.__cause__ = RemoteTraceback(tb)
                    raise exc
                task, w.task = w.task, None
                w.done += 1
                on_done(task, rest[0])
                if self.recycle_after and w.done >= self.recycle_after:
                    self._retire(w)
                    if pending:
                        w = self._spawn()
                if pending:
                    w.send(pending.popleft(), ws)

    def drain(self, on_done: OnDone) -> None:
        """After an interrupt: record results already sent by workers (nothing else).

        A dead worker's pipe is skipped; an error of `on_done` itself (a manifest that cannot be
        written) propagates: the caller must not report shards as kept that were never recorded."""
        for w in self.workers:
            while w.task is not None:
                try:
                    if not w.conn.poll(0):
                        break
                    msg = w.conn.recv()
                except (EOFError, OSError):
                    break
                if not (msg and msg[0] == "ok"):
                    break
                task, w.task = w.task, None
                on_done(task, msg[2])

    def kill(self) -> None:
        """SIGKILL every worker now (errors, interrupts); results already sent stay readable."""
        for w in self.workers:
            w.kill()

    def close(self) -> None:
        """Stop every remaining worker (gracefully if still running) and close the pipes."""
        ws, self.workers = self.workers, []
        for w in ws:
            if w.proc.is_alive():
                w.stop()
            else:
                w.close()


def run_dask(tasks: Iterable[Task], ws: WorkerSettings, scheduler: str, workers: int, on_done: OnDone) -> None:
    """`scheduler`: 'dask-local' (a LocalCluster of `workers` processes) or a 'tcp://host:port' address."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
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
        collect(client, tasks, ws, on_done)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _result(future, watch: Callable[[], None] | None):
    """`future.result()`, still calling `watch` while it waits: a future `as_completed` hands out
    may not be finished after all (its worker's job was killed: Dask waits for the task to be
    computed again, by a worker that will never come), and only the watch can then stop the run."""
    if watch is None:
        return future.result()
    while True:
        try:
            return future.result(timeout=0.5)
        except (TimeoutError, asyncio.TimeoutError):
            watch()


def collect(client, tasks: list[Task], ws: WorkerSettings, on_done: OnDone,
            watch: Callable[[], None] | None = None) -> None:
    """Submit every task to a Dask `client`, record each shard as it finishes.

    `watch` (optional) is called about every 0.2 s while shards are outstanding and may raise to
    stop the run (pipeline/slurm.py: a worker job that ended).  On any error or interrupt, shards
    that already finished are still recorded; the rest are left to the caller's cleanup."""
    from dask.distributed import as_completed

    futs: dict = {}
    recorded: set = set()
    try:
        futs = {client.submit(render_shard, t, ws, key=f"msps-{t.name}-{t.config_json.__hash__()}", pure=False): t
                for t in tasks}
        ac = as_completed(list(futs))
        while not ac.is_empty():
            if watch is not None and not ac.has_ready():
                watch()
                time.sleep(0.2)
                continue
            for f in ac.next_batch(block=watch is None):
                info = _result(f, watch)
                recorded.add(f.key)
                on_done(futs[f], info)
    except BaseException:  # error or interrupt: keep shards that finished, quietly cancel the rest
        import logging

        for name in ("distributed", "distributed.worker", "distributed.worker.state_machine"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
        outstanding = [f for f in futs if f.key not in recorded and f.status != "finished"]
        if outstanding:  # stop the cluster from rendering shards nobody will record
            try:
                client.cancel(outstanding)
            except Exception:  # noqa: BLE001 - a lost scheduler: closing the client below ends them
                pass
        for f, t in futs.items():
            if f.key not in recorded and f.status == "finished":
                try:
                    info = f.result(timeout=1)
                except Exception:  # noqa: BLE001 - the result is gone: --resume re-renders that shard
                    continue
                on_done(t, info)  # a failed manifest write surfaces
        raise
