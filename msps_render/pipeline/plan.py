"""Plan: a dataset config + root seed -> one task per shard.

Seeds: `SeedSequence(seed).spawn(n_shards)` gives shard k its own stream, and
shard k spawns one child per frame, so a frame's content depends only on
(seed, shard, frame) - never on worker count, order or resumes.  Sweep
conditions reuse the same shard seeds: condition A and B render the same
objects and materials, only the swept setting differs (what robustness
comparisons need).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from msps_render.pipeline.config import DatasetConfig, condition_config, config_json


@dataclass(frozen=True)
class Task:
    index: int  # global shard index
    name: str  # file name, e.g. shard-00003.h5
    condition: str  # '' without a sweep
    shard_in_condition: int
    seed: int  # root seed
    config_json: str  # resolved config of this condition (no sweep)
    sweep_key: str | None = None  # the swept config key (None without a sweep)
    condition_value: Any = None  # its value in this condition (typed, as in the config)


def plan(cfg: DatasetConfig) -> list[Task]:
    tasks = []
    for c, (cond, value) in enumerate(cfg.conditions()):
        ccfg = cfg if cfg.sweep is None else condition_config(cfg, value)
        cj = config_json(ccfg)
        for k in range(cfg.dataset.n_shards):
            i = c * cfg.dataset.n_shards + k
            tasks.append(Task(index=i, name=f"shard-{i:05d}.h5", condition=cond, shard_in_condition=k,
                              seed=cfg.dataset.seed, config_json=cj,
                              sweep_key=cfg.sweep.key if cfg.sweep else None, condition_value=value))
    return tasks


def frame_rngs(task: Task, n_frames: int) -> list[np.random.Generator]:
    shard_ss = np.random.SeedSequence(task.seed).spawn(task.shard_in_condition + 1)[task.shard_in_condition]
    return [np.random.default_rng(s) for s in shard_ss.spawn(n_frames)]


SENSOR_STREAM = 0x53454E53  # "SENS"


def sensor_rng(task: Task, j: int) -> np.random.Generator:
    """Frame j's sensor-noise stream: its own, keyed by the frame seed, so the recorded image can be
    re-created from a stored scene and its frame seed, and sampler changes never move the noise."""
    return np.random.default_rng([frame_seed(task, j), SENSOR_STREAM])


def frame_seed(task: Task, j: int) -> int:
    """A printable integer identifying frame j's stream (provenance only)."""
    return int(np.random.SeedSequence(task.seed).spawn(task.shard_in_condition + 1)[task.shard_in_condition]
               .spawn(j + 1)[j].generate_state(1)[0])
