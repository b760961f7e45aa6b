"""Dataset pipeline: config -> plan (seeded tasks) -> execute (local pool / Dask) -> shards + manifest."""
from msps_render.pipeline.config import DatasetConfig, config_hash, load_config
from msps_render.pipeline.plan import Task, plan

__all__ = ["DatasetConfig", "load_config", "config_hash", "Task", "plan"]
