"""What a dataset config will make, without rendering it: `msps config show`.

`describe(cfg)` gives the exact plan (conditions, shards, frames: the same
`plan()` that `msps render` executes).  With `probe > 0` it also renders that
many real frames of the plan (same seeds, resolution, spp and storage
settings as the render would use, through the same `render_shard`) into a
temporary directory, measures them and deletes them:

* patches: counted on the masks of `masks` frames of the plan (same seeds; one
  ray per pixel, no light transport, so cheap): frames x the sample mean per
  condition, +- 2 standard errors; exact when every frame is counted;
* render time: the probe's mean render seconds per frame (after one uncounted
  warm-up frame) x frames, + the warm-up's extra (kernel compilation, once per
  worker), one process;
* disk: raw bytes per patch from the storage dtypes x a compression factor
  measured on the probe shard, plus the measured bytes per frame record and per
  shard (HDF5 metadata).
"""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from msps_render.dataset.sizes import raw_patch_bytes, storage_bytes
from msps_render.errors import InputError
from msps_render.patches import patchify
from msps_render.pipeline.config import DatasetConfig
from msps_render.pipeline.config_toml import config_toml
from msps_render.pipeline.execute import WorkerSettings, render_shard
from msps_render.pipeline.plan import Task, frame_rngs, frame_seed, plan
from msps_render.pipeline.validate import validate_inputs
from msps_render.render.mask import scene_mask
from msps_render.render.memory import release_frame_memory
from msps_render.render.variant import activate, resolve_variant
from msps_render.scene.sample import sample_scene


@dataclass
class Condition:
    name: str  # '' without a sweep
    value: object
    shards: int
    frames: int


@dataclass
class Estimate:
    """Measured on `probe_frames` real frames; every number says what it rests on."""

    probe_frames: int
    probe_from: list[str]  # e.g. ["shard-00000.h5 frames 0-1 (slant_deg=20)"]
    variant: str
    probe_conditions: int  # sweep conditions the rendered probe covered
    mask_conditions: int  # sweep conditions the mask count covered
    mask_frames: int  # frames whose masks were computed (one ray per pixel) to count patches
    mask_seconds: float
    patches_per_frame: list[int]  # of each mask frame
    patches: int  # estimate for the whole dataset
    patches_margin: int | None  # +- 2 standard errors (None: spread unknown)
    exact: bool  # every frame of the dataset was counted
    seconds_per_frame: float  # render seconds (mean over probe frames, after a warm-up frame)
    startup_seconds: float  # warm-up frame minus a frame: kernel compilation, once per worker
    render_seconds: float  # whole dataset, one process: startup + frames x seconds_per_frame
    probe_wall_seconds: float  # what the probe itself took (Mitsuba start-up included)
    raw_bytes_per_patch: int
    compression_factor: float  # stored / raw bytes of the probe's patch arrays
    bytes_per_frame: float  # frame records (+ whole frames when stored), measured
    bytes_per_shard: float  # HDF5 metadata per file, measured
    disk_bytes: int


@dataclass
class Description:
    config_toml: str
    n_conditions: int
    n_shards: int
    frames_per_shard: int
    n_frames: int
    conditions: list[Condition]
    sweep_key: str | None
    resolution: tuple[int, int]
    spp: int
    patch_size: int
    patch_stride: int
    min_coverage: float
    rig: str | None
    storage: dict
    estimate: Estimate | None = None
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def describe(cfg: DatasetConfig, probe: int = 0, variant: str | None = None,
             threads: int | None = None, masks: int = 32) -> Description:
    """The resolved config, the plan and (probe > 0) estimates: time and disk measured on `probe`
    rendered frames, patches counted on the masks of `masks` frames (at least the probe's)."""
    d = cfg.dataset
    tasks = plan(cfg)
    conds = []
    for name, value in cfg.conditions():
        n = sum(1 for t in tasks if t.condition == name)
        conds.append(Condition(name=name, value=value, shards=n, frames=n * d.frames_per_shard))
    cam = cfg.scene.camera
    desc = Description(
        config_toml=config_toml(cfg), n_conditions=len(conds), n_shards=len(tasks),
        frames_per_shard=d.frames_per_shard, n_frames=len(tasks) * d.frames_per_shard, conditions=conds,
        sweep_key=cfg.sweep.key if cfg.sweep else None, resolution=(cam.width, cam.height),
        spp=cfg.scene.integrator.spp, patch_size=d.patches.size, patch_stride=d.patches.stride,
        min_coverage=d.patches.min_coverage, storage=d.storage.model_dump(), rig=_rig_line(cfg))
    if probe > 0:
        desc.estimate = _probe(cfg, tasks, probe, variant, threads, masks)
    return desc


def probe_frames(tasks: list[Task], n_conditions: int, frames_per_shard: int, n: int) -> dict[str, int]:
    """{shard name: how many of its first frames to probe}.  Probe frame i goes to condition
    i mod C as that condition's next frame in plan order, so every condition is probed once
    n >= C, and n >= all frames probes the whole dataset."""
    per_cond = len(tasks) // n_conditions  # shards per condition (plan order: condition-major)
    out: dict[str, int] = {}
    for i in range(min(n, len(tasks) * frames_per_shard)):
        c, k = i % n_conditions, i // n_conditions  # k-th probe frame of condition c
        name = tasks[c * per_cond + k // frames_per_shard].name
        out[name] = out.get(name, 0) + 1
    return out


def mask_counts(cfg: DatasetConfig, tasks: list[Task], m: int, variant: str,
                threads: int | None) -> dict[str, list[int]]:
    """{condition: patch count of each sampled frame}: `m` frames of the plan (same seeds as the
    render, picked like `probe_frames`), their masks from one ray per pixel (no rendering)."""
    F = cfg.dataset.frames_per_shard
    out: dict[str, list[int]] = {}
    by_name = {t.name: t for t in tasks}
    for name, k in probe_frames(tasks, len(cfg.conditions()), F, m).items():
        t = by_name[name]
        tcfg = DatasetConfig.model_validate_json(t.config_json)
        p = tcfg.dataset.patches
        for j, rng in enumerate(frame_rngs(t, F)[:k]):
            spec = sample_scene(tcfg.scene, rng, seed=frame_seed(t, j), frame_index=t.shard_in_condition * F + j)
            mask = scene_mask(spec, variant, threads)
            z = np.broadcast_to(np.zeros(1, np.float32), mask.shape + (3,))
            n = len(patchify(SimpleNamespace(mask=mask, image=z, normal=z), p.size, p.stride, p.min_coverage))
            out.setdefault(t.condition, []).append(n)
            release_frame_memory()
    return out


def _probe(cfg: DatasetConfig, tasks: list[Task], n: int, variant: str | None,
           threads: int | None, masks: int) -> Estimate:
    validate_inputs(cfg, getattr(cfg, "_source", None))
    d = cfg.dataset
    C = len(cfg.conditions())
    F = d.frames_per_shard
    mode = "spectral" if cfg.scene.mode == "spectral" else "rgb"
    variant = resolve_variant(mode, variant)
    t0 = time.perf_counter()
    activate(variant, threads)
    picks = probe_frames(tasks, C, F, n)
    by_name = {t.name: t for t in tasks}
    render_s, raw, stored_patches, stored_frames, other, frames_done = 0.0, 0, 0, 0, 0, 0
    rig = cfg.scene.rig
    lights, shots, channels, near = rig.image_shape() if rig is not None else (3, 1, 3, False)
    raw1 = raw_patch_bytes(d.patches.size, d.storage.image_dtype, d.storage.normal_dtype, shots, channels, near,
                           lights if d.storage.store_shadows else 0)
    probe_from = []
    tmp = Path(tempfile.mkdtemp(prefix="msps-probe-"))
    ws = WorkerSettings(out_dir=str(tmp), variant=variant, threads=threads)
    try:
        (tmp / "shards").mkdir()
        # warm-up: frame 0 once, not counted (Mitsuba compiles its kernels on the first render of a
        # process; a worker pays that once, so it is a per-worker cost, not a per-frame one)
        warm_s = render_shard(_first_frames(tasks[0], 1), ws)["render_seconds"]
        (tmp / "shards" / tasks[0].name).unlink()
        for name, m in picks.items():
            t = by_name[name]
            info = render_shard(_first_frames(t, m), ws)
            sizes = storage_bytes(tmp / "shards" / name)
            render_s += info["render_seconds"]
            raw += raw1 * info["n_patches"]
            stored_patches += sizes["patches"]
            stored_frames += sizes["frames"]
            other += sizes["other"]
            frames_done += m
            probe_from.append(f"{name} frame{'s' if m > 1 else ''} 0{f'-{m - 1}' if m > 1 else ''}"
                              + (f" ({t.condition})" if t.condition else ""))
            (tmp / "shards" / name).unlink()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    wall = time.perf_counter() - t0
    t1 = time.perf_counter()
    per_cond = mask_counts(cfg, tasks, max(masks, frames_done), variant, threads)
    mask_s = time.perf_counter() - t1
    patches, margin, exact = patch_estimate(per_cond, {c: sum(1 for t in tasks if t.condition == c) * F
                                                       for c, _ in cfg.conditions()})
    n_frames = len(tasks) * F
    factor = stored_patches / raw if raw else 1.0
    spf = render_s / frames_done
    startup = max(0.0, warm_s - spf)
    bpf = stored_frames / frames_done
    bps = other / len(picks)
    disk = patches * raw1 * factor + n_frames * bpf + len(tasks) * bps
    return Estimate(probe_frames=frames_done, probe_from=probe_from, variant=variant,
                    probe_conditions=len({by_name[p].condition for p in picks}), mask_conditions=len(per_cond),
                    mask_frames=sum(len(v) for v in per_cond.values()), mask_seconds=mask_s,
                    patches_per_frame=[n for v in per_cond.values() for n in v], patches=patches,
                    patches_margin=margin, exact=exact, seconds_per_frame=spf, startup_seconds=startup,
                    render_seconds=startup + spf * n_frames,
                    probe_wall_seconds=wall, raw_bytes_per_patch=raw1, compression_factor=factor,
                    bytes_per_frame=bpf, bytes_per_shard=bps, disk_bytes=int(round(disk)))


def _first_frames(t: Task, m: int) -> Task:
    """Task `t` cut to its first `m` frames: the same seeds as the render.  (With shape.mesh_order =
    'cycle' a probe in a later shard may draw another mesh; patch counts come from `mask_counts`.)"""
    tcfg = json.loads(t.config_json)
    tcfg["dataset"]["frames_per_shard"] = m
    return dataclasses.replace(t, config_json=json.dumps(tcfg, sort_keys=True, separators=(",", ":")))


def patch_estimate(counts: dict[str, list[int]], frames: dict[str, int]) -> tuple[int, int | None, bool]:
    """(estimated patches, margin, exact) from sampled per-frame counts of each condition.

    Per condition: frames x the sample mean (a condition without samples uses all samples).
    Margin: 2 standard errors of that total (sampling without replacement, so the finite
    population correction applies: 0 when every frame was sampled); None when a condition
    has a single sample and no other samples give a spread.
    """
    pooled = [n for v in counts.values() for n in v]
    total, var, exact, unknown = 0.0, 0.0, True, False
    for cond, N in frames.items():
        x = counts.get(cond) or pooled
        k = len(x)
        mean = sum(x) / k
        total += N * mean
        if cond in counts and k >= N:
            continue  # every frame of this condition sampled: exact
        exact = False
        spread = x if k > 1 else pooled
        if len(spread) < 2:
            unknown = True
            continue
        mu = sum(spread) / len(spread)
        sd2 = sum((v - mu) ** 2 for v in spread) / (len(spread) - 1)
        fpc = (N - k) / (N - 1) if N > 1 else 0.0
        var += N * N * sd2 / k * max(fpc, 0.0)
    if exact:
        return int(round(total)), 0, True
    return int(round(total)), (None if unknown else int(math.ceil(2 * math.sqrt(var)))), False


# ------------------------------------------------------------------ text
def _bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} TB"


def _duration(s: float) -> str:
    if s < 120:
        return f"{s:.1f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def _rig_line(cfg: DatasetConfig) -> str | None:
    """What the rig costs per patch, against a three-light patch of the same size and dtypes."""
    rig = cfg.scene.rig
    if rig is None:
        return None
    try:
        lights, shots, channels, near = rig.image_shape()
    except InputError as e:  # a light file not here (e.g. $MSPS_TEST_DATA unset): the plan without it
        return f"rig {rig.layout}: lights from {rig.file} ({e})"
    d = cfg.dataset
    one = raw_patch_bytes(d.patches.size, d.storage.image_dtype, d.storage.normal_dtype)
    mine = raw_patch_bytes(d.patches.size, d.storage.image_dtype, d.storage.normal_dtype, shots, channels, near,
                           lights if d.storage.store_shadows else 0)
    line = (f"rig {rig.describe()}: {shots} image(s) of {d.patches.size}x{d.patches.size}x{channels} per patch"
            f"{f' + {lights} shadow codes' if d.storage.store_shadows else ''}, "
            f"{mine / one:.1f}x the raw bytes of a three-light patch")
    if shots > 16:
        line += ("; keep image_dtype float16, and train on a light subset per sample (the loader's "
                 "`lights_per_sample`, as PS-FCN trains on 32 of its images)")
    return line


def plan_text(desc: Description) -> str:
    """The plan and the estimates as TOML comments (so `config show` output stays valid TOML)."""
    e = desc.estimate
    L = ["# ---- plan (nothing rendered) ----" if e is None else
         f"# ---- plan, with estimates from {e.probe_frames} probe frame(s) rendered now (temp dir, deleted) ----"]
    W, H = desc.resolution
    L.append(f"# conditions: {desc.n_conditions}" + (f" (sweep over {desc.sweep_key})" if desc.sweep_key else ""))
    for c in desc.conditions:
        L.append(f"#   {c.name or '(single condition)'}: {c.shards} shards, {c.frames} frames")
    L.append(f"# shards: {desc.n_shards} ({desc.n_conditions} condition(s) x "
             f"{desc.n_shards // max(1, desc.n_conditions)}), frames: {desc.n_frames} "
             f"({desc.frames_per_shard} per shard)")
    st = desc.storage
    L.append(f"# frames {W}x{H} px, {desc.spp} spp; patches {desc.patch_size} px, stride {desc.patch_stride}, "
             f"kept at >= {desc.min_coverage:g} object coverage; storage {st['compression']}, "
             f"image {st['image_dtype']}, normal {st['normal_dtype']}"
             + (", whole frames stored" if st["store_frames"] else "")
             + (" with per-light images" if st.get("store_per_light") else ""))
    if desc.rig:
        L.append(f"# {desc.rig}")
    if e is None:
        L.append("# estimates: none (nothing rendered); `--probe N` renders N frames of the plan into a temp "
                 "dir to estimate patches, render time and disk")
        return "\n".join(L) + "\n"
    L.append(f"# ---- estimates: {e.probe_frames} probe frame(s) rendered with {e.variant} into a temp dir "
             f"(deleted): {'; '.join(e.probe_from)} ----")
    if e.exact:
        L.append(f"# patches: {e.patches} (exact: counted on the masks of all {e.mask_frames} frames)")
    else:
        if e.patches_margin is None:
            pm = " (spread unknown: one frame; raise --masks)"
        elif e.patches_margin == 0:
            pm = " (every sampled frame gave the same count)"
        else:
            pm = f" +- {e.patches_margin} (2 standard errors)"
        lo, hi = min(e.patches_per_frame), max(e.patches_per_frame)
        L.append(f"# patches: ~{e.patches}{pm}, from the masks of {e.mask_frames} of the {desc.n_frames} frames "
                 f"(same seeds; one ray per pixel, {e.mask_seconds:.1f} s): {lo}..{hi} patches per frame")
    if e.probe_conditions < desc.n_conditions or e.mask_conditions < desc.n_conditions:
        L.append(f"# (the probe rendered {e.probe_conditions} and counted masks of {e.mask_conditions} of the "
                 f"{desc.n_conditions} conditions; the others are assumed alike: raise --probe / --masks)")
    L.append(f"# render time: ~{_duration(e.render_seconds)} in one process: {e.seconds_per_frame:.2f} s/frame "
             f"measured now on this machine after a warm-up frame, + {e.startup_seconds:.1f} s kernel compilation "
             f"once per worker (with --workers W on W idle cores: ~1/W of the frame time); the probe took "
             f"{e.probe_wall_seconds:.1f} s")
    L.append(f"# disk: ~{_bytes(e.disk_bytes)} ({e.raw_bytes_per_patch} B/patch raw from the dtypes x "
             f"{e.compression_factor:.2f} measured {st['compression']} compression, "
             f"+ {_bytes(e.bytes_per_frame)}/frame record"
             + (" incl. whole frames" if st["store_frames"] else "")
             + f", + {_bytes(e.bytes_per_shard)}/shard metadata)")
    return "\n".join(L) + "\n"
