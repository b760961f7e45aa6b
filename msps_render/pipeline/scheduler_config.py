"""`[scheduler]`: where a render runs (Slurm job resources), not what it renders.

A module of its own so that the config (pipeline/config.py) can hold it without importing the
scheduler code that runs shards (pipeline/slurm.py imports the execution loop).
"""
from __future__ import annotations

from pydantic import Field

from msps_render.config_io import StrictModel


class SlurmSettings(StrictModel):
    """Resources of each worker job (`[scheduler.slurm]`; flags of `msps render` override them)."""

    partition: str | None = Field(None, description="Slurm partition of the worker jobs (sbatch -p); "
                                                     "none: the cluster's default partition")
    account: str | None = Field(None, description="account charged for the jobs (sbatch -A)")
    cores: int = Field(1, ge=1, le=1024, description="CPUs per worker job (sbatch --cpus-per-task); the "
                                                     "worker renders with that many threads unless "
                                                     "--threads or MSPS_THREADS says otherwise")
    memory: str = Field("4GB", description="memory per worker job (sbatch --mem), e.g. '4GB'; also the "
                                           "Dask worker's memory limit")
    walltime: str = Field("04:00:00", description="time limit per worker job (sbatch -t); a run that "
                                                  "outlives its jobs stops and finishes with --resume")
    sbatch: list[str] = Field(default_factory=list, description="extra sbatch options, one per item, e.g. "
                                                                "['--qos=low', '--constraint=avx2']")
    prologue: list[str] = Field(default_factory=list, description="shell lines run in each job before "
                                                                  "the worker starts (module load ...)")
    log_dir: str | None = Field(None, description="directory for the jobs' stdout/stderr (on a shared "
                                                  "filesystem); none: discarded")


class SchedulerSection(StrictModel):
    """How to run a render, not what it renders: excluded from the config hash and the shards."""

    slurm: SlurmSettings = SlurmSettings()
