"""Render shards on a Slurm cluster: `msps render CONFIG --scheduler slurm --workers N`.

N Slurm jobs (dask-jobqueue's `SLURMCluster`), each one Dask worker process that renders one shard at
a time with `cores` threads; the driver (this process) runs the Dask scheduler, hands out shards
(`execute.collect`, the same loop as any Dask run) and alone writes the manifest.  Workers run this
very interpreter (`sys.executable`, so the same venv and the same msps) and write shards into `--out`,
which must therefore be on a filesystem the compute nodes share.

Why the checks around dask-jobqueue: it submits jobs in the background and only logs what goes
wrong, and a job that ends (cancelled, timed out, killed) just leaves its shards waiting forever.  So
the job script is first tried with `sbatch --test-only` (a bad partition, time or memory is one clear
line before anything is rendered), submission errors are caught, and every few seconds `squeue` is
asked about our jobs: one that ended while shards were still to do stops the run (`WorkerDied`,
finished shards kept, `--resume` finishes).  On Ctrl-C / SIGTERM / any error the cluster is closed,
which `scancel`s every job it submitted.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Iterable

from msps_render.pipeline.scheduler_config import SchedulerSection, SlurmSettings  # noqa: F401 (re-exported)
from msps_render.errors import InputError, WorkerDied, brief, format_validation_error


POLL_SECONDS = 2.0  # how often squeue is asked about our jobs (one call for all of them)
ALIVE = {"PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "SUSPENDED", "REQUEUED", "RESIZING", "SIGNALING",
         "STAGE_OUT", "REQUEUE_HOLD", "REQUEUE_FED"}


def _slurm_setting(key: str) -> str:
    return f"scheduler.slurm.{key}"


def with_flags(s: SlurmSettings, scheduler: str | None, **flags) -> SlurmSettings:
    """`s` with the `msps render` flags that were given (`--sbatch` adds to the config's list)."""
    given = {k: v for k, v in flags.items() if v not in (None, [], ())}
    if not given:
        return s
    if scheduler != "slurm":
        raise InputError(f"--{next(iter(given))}", "only applies with --scheduler slurm")
    data = s.model_dump()
    for k, v in given.items():
        data[k] = data[k] + list(v) if k == "sbatch" else v
    try:
        return SlurmSettings.model_validate(data)
    except ValueError as e:
        bad = next((k for k in given if k in str(e)), next(iter(given)))
        raise InputError(f"--{bad}", format_validation_error(e)) from None


def render_threads(s: SlurmSettings, threads: int | None) -> int:
    """Render threads per worker: --threads, else MSPS_THREADS (seen by the driver), else the job's CPUs."""
    from msps_render.render.variant import env_threads

    return int(threads or env_threads() or s.cores)


def _import_jobqueue():
    """`import dask_jobqueue`, keeping our SIGINT handler: its runner module replaces it on import with
    `sys.exit()`, which would turn Ctrl-C into a silent exit 0 that skips our cleanup."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    old = signal.getsignal(signal.SIGINT) if main else None
    try:
        import dask_jobqueue
        import dask_jobqueue.runner  # noqa: F401 - the module that sets the handler
    finally:
        if main and old is not None and signal.getsignal(signal.SIGINT) is not old:
            signal.signal(signal.SIGINT, old)
    return dask_jobqueue


def preflight(s: SlurmSettings) -> None:
    """What can be known before any job: dask-jobqueue and sbatch installed."""
    try:
        _import_jobqueue()
    except ImportError:
        raise InputError("--scheduler slurm", "needs dask-jobqueue (pip install 'msps[slurm]')") from None
    if shutil.which("sbatch") is None:
        raise InputError("--scheduler slurm", "sbatch not found on PATH (run on a Slurm login node, or use "
                                              "--scheduler dask-local)")


def make_cluster(s: SlurmSettings, submitted: list[str], failures: list[BaseException]):
    """A `SLURMCluster` of one-worker jobs whose submitted job IDs and submission errors are recorded."""
    import logging

    _import_jobqueue()
    from dask_jobqueue import SLURMCluster
    from dask_jobqueue.slurm import SLURMJob

    for name in ("distributed", "dask_jobqueue", "tornado", "asyncio"):  # our own one-line errors instead
        logging.getLogger(name).setLevel(logging.CRITICAL)

    class Job(SLURMJob):
        async def start(self):
            try:
                await super().start()
            except BaseException as e:
                failures.append(e)
                raise
            submitted.append(str(self.job_id))

    extra = list(s.sbatch)
    if s.log_dir is None:
        extra += ["--output=/dev/null", "--error=/dev/null"]
    else:
        Path(s.log_dir).mkdir(parents=True, exist_ok=True)
    return SLURMCluster(job_cls=Job, cores=1, processes=1, job_cpu=s.cores, memory=s.memory, queue=s.partition,
                        account=s.account, walltime=s.walltime, job_extra_directives=extra,
                        job_script_prologue=list(s.prologue), log_directory=s.log_dir, python=sys.executable,
                        name="msps-worker", scheduler_options={"dashboard_address": None},
                        shared_temp_directory=tempfile.gettempdir())


def check_job_script(script: str) -> None:
    """`sbatch --test-only` the job script: Slurm's own verdict on partition, time, memory, options."""
    with tempfile.NamedTemporaryFile("w", suffix=".sh", prefix="msps-slurm-", delete=False) as f:
        f.write(script)
    try:
        r = subprocess.run(["sbatch", "--test-only", f.name], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        raise InputError("--scheduler slurm", "sbatch --test-only did not answer in 60 s "
                                              "(is slurmctld reachable?)") from None
    finally:
        os.unlink(f.name)
    if r.returncode != 0:
        raise InputError(_blame(r.stderr), f"Slurm refuses the worker job: {_sbatch_error(r.stderr)}")


def _sbatch_error(stderr: str) -> str:
    """The most telling line of sbatch's complaint, without its 'sbatch: error:' prefix."""
    lines = [ln.split("error:", 1)[-1].strip() for ln in stderr.splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.lower().startswith("batch job submission failed")] or lines
    return brief(lines[0] if lines else "sbatch failed", 160)


def _blame(stderr: str) -> str:
    """The setting sbatch's message points at (for the error line's source)."""
    t = stderr.lower()
    for words, key in ((("partition",), "partition"), (("time limit", "time specification"), "walltime"),
                       (("memory", "mem "), "memory"), (("account",), "account"),
                       (("cpu", "processor"), "cores")):
        if any(w in t for w in words):
            return _slurm_setting(key)
    return _slurm_setting("sbatch")


def job_states(ids: list[str]) -> dict[str, tuple[str, str]]:
    """{job id: (state, reason)} of the jobs Slurm still knows (finished ones for MinJobAge seconds)."""
    if not ids:
        return {}
    try:
        r = subprocess.run(["squeue", "-h", "-t", "all", "-o", "%i|%T|%r", "-j", ",".join(ids)],
                           capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return {i: ("UNKNOWN", "") for i in ids}  # squeue unreachable: do not call jobs dead
    if r.returncode != 0 and "invalid job id" not in r.stderr.lower():
        return {i: ("UNKNOWN", "") for i in ids}
    out = {}
    for ln in r.stdout.splitlines():
        parts = ln.strip().split("|")
        if len(parts) == 3:
            out[parts[0]] = (parts[1], parts[2])
    return out


class JobWatch:
    """Called by the collect loop while shards are outstanding: raises when a worker job is gone."""

    def __init__(self, submitted: list[str], failures: list[BaseException], workers: int):
        self.submitted, self.failures, self.workers = submitted, failures, workers
        self.next = 0.0

    def __call__(self) -> None:
        if self.failures:
            e = self.failures[0]
            raise InputError(_blame(str(e)), f"Slurm refused a worker job: {_sbatch_error(str(e))}")
        if time.monotonic() < self.next:
            return
        self.next = time.monotonic() + POLL_SECONDS
        ids = list(self.submitted)
        states = job_states(ids)
        for i in ids:
            state, reason = states.get(i, ("GONE", ""))
            if state == "UNKNOWN" or state in ALIVE:
                continue
            why = f"{state}" + (f", {reason}" if reason and reason != "None" else "")
            if state == "GONE":
                why = "no longer known to Slurm"
            raise WorkerDied(f"Slurm job {i} (a render worker) ended ({why}) before the render finished; "
                             f"finished shards are kept, rerun with --resume")


def run_slurm(tasks: Iterable, ws, workers: int, on_done, settings: SlurmSettings | None,
              threads: int | None = None) -> None:
    """Render `tasks` on `workers` Slurm jobs described by `settings` (see the module docstring)."""
    from dask.distributed import Client

    from msps_render.pipeline.execute import collect

    s = settings or SlurmSettings()
    preflight(s)
    tasks = list(tasks)
    if not tasks:
        return
    ws = replace(ws, threads=render_threads(s, threads))
    submitted: list[str] = []
    failures: list[BaseException] = []
    cluster = client = None
    try:
        try:
            cluster = make_cluster(s, submitted, failures)
        except (ValueError, TypeError) as e:  # e.g. a memory string dask cannot parse
            raise InputError(_slurm_setting("memory") if "byte" in str(e).lower() else "[scheduler.slurm]",
                             brief(str(e), 160)) from None
        check_job_script(cluster.job_script())
        n = max(1, min(int(workers), len(tasks)))
        cluster.scale(jobs=n)
        client = Client(cluster)
        collect(client, tasks, ws, on_done, watch=JobWatch(submitted, failures, n))
    finally:
        _close(client, cluster, submitted)


def _close(client, cluster, submitted: list[str]) -> None:
    """Close the client and the cluster, then `scancel` every job we submitted (also after an
    interrupt or a failed close; cancelling a finished job is harmless) and wait until Slurm has
    ended them: a job still shutting down may be writing a shard, so the driver's clean-up of
    partial shards (`remove_temporaries`) must come after it (a `.shard-N.h5.tmp` was left once)."""
    for thing in (client, cluster):
        if thing is None:
            continue
        try:
            thing.close()
        except BaseException:  # noqa: BLE001 - closing is best effort; the cancel below is not
            pass
    if submitted:
        try:
            subprocess.run(["scancel", *submitted], capture_output=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return
        wait_ended(submitted)


def wait_ended(ids: list[str], timeout: float = 60.0) -> bool:
    """Wait until none of the jobs `ids` is alive (COMPLETING included: its processes are still being
    killed); False after `timeout` seconds or when squeue cannot say."""
    t_end = time.monotonic() + timeout
    while True:
        states = job_states(list(ids))
        if any(st == "UNKNOWN" for st, _ in states.values()):
            return False
        if not any(st in ALIVE for st, _ in states.values()):
            return True
        if time.monotonic() > t_end:
            return False
        time.sleep(0.2)
