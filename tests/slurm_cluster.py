"""A real, private, single-node Slurm cluster for tests: munged + slurmctld + slurmd on localhost.

Why real daemons rather than a fake `sbatch`: the behaviour under test (jobs queued, started,
cancelled on Ctrl-C, dying) is Slurm's, and Debian's `slurm-wlm` and `munge` run it as root on one
machine in a second.  Everything lives in one temporary directory (munge key and socket, slurm.conf,
state, spool, logs) on free ports, so the host's own Slurm or munge (if any) is never touched; the
daemons run in the foreground (`-F` / `-D`), so the PIDs we hold are theirs, and `stop()` ends exactly
those processes (after cancelling the jobs submitted to this cluster), never anything found by name.

`SlurmCluster.start()` raises `Unavailable(reason)` where this cannot run: not root, a binary
missing, or the node not idle within `timeout` seconds; the pytest fixture turns it into a skip.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

BINARIES = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "sinfo", "scancel", "scontrol")
PARTITION = "msps"  # the cluster's only (default) partition


class Unavailable(RuntimeError):
    """A Slurm test cluster cannot run here (the message says why)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _node() -> tuple[str, int, int]:
    """(hostname, CPUs, MiB of memory to offer) of this machine, as slurmd will see it."""
    name = socket.gethostname().split(".")[0]
    mem_kib = next(int(ln.split()[1]) for ln in Path("/proc/meminfo").read_text().splitlines()
                   if ln.startswith("MemTotal:"))
    return name, os.cpu_count() or 1, int(mem_kib / 1024 * 0.9)  # below the real total: never drained


SLURM_CONF = """\
ClusterName=msps-test
SlurmctldHost={host}(127.0.0.1)
SlurmctldPort={ctld_port}
SlurmdPort={slurmd_port}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={munge_socket}
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SwitchType=switch/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MinJobAge=600
KillWait=2
StateSaveLocation={d}/state
SlurmdSpoolDir={d}/spool
SlurmctldPidFile={d}/slurmctld.pid
SlurmdPidFile={d}/slurmd.pid
SlurmctldLogFile={d}/slurmctld.log
SlurmdLogFile={d}/slurmd.log
NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={mem_mib} State=UNKNOWN
PartitionName={partition} Nodes={host} Default=YES MaxTime=INFINITE State=UP
"""


class SlurmCluster:
    """`start()`, use `env` (SLURM_CONF) for every client command, `stop()`."""

    def __init__(self, timeout: float = 30.0):
        self.timeout = timeout
        self.dir: Path | None = None
        self.procs: list[subprocess.Popen] = []
        self.env: dict[str, str] = {}
        self.conf: Path | None = None

    # -------------------------------------------------------------- start
    def start(self) -> "SlurmCluster":
        if os.geteuid() != 0:
            raise Unavailable("needs root (slurmd runs jobs as their user)")
        missing = [b for b in BINARIES if shutil.which(b) is None]
        if missing:
            raise Unavailable(f"not installed: {', '.join(missing)} (apt-get install slurm-wlm munge)")
        self.dir = Path(tempfile.mkdtemp(prefix="msps-slurm-"))  # short: the munge socket path must fit
        d = self.dir
        for sub in ("state", "spool", "munge"):
            (d / sub).mkdir()
        os.chmod(d / "munge", 0o700)
        key = d / "munge" / "munge.key"
        key.write_bytes(os.urandom(1024))
        os.chmod(key, 0o400)
        sock = d / "munge" / "munge.socket"
        host, cpus, mem = _node()
        self.conf = d / "slurm.conf"
        self.conf.write_text(SLURM_CONF.format(host=host, ctld_port=_free_port(), slurmd_port=_free_port(),
                                               munge_socket=sock, d=d, cpus=cpus, mem_mib=mem,
                                               partition=PARTITION))
        self.env = {"SLURM_CONF": str(self.conf)}
        env = dict(os.environ, **self.env)
        try:
            self._spawn(["munged", "-F", "-f", f"--key-file={key}", f"--socket={sock}",
                         f"--pid-file={d / 'munge' / 'munged.pid'}", f"--log-file={d / 'munge' / 'munged.log'}",
                         f"--seed-file={d / 'munge' / 'munged.seed'}"], env, d / "munged.out")
            self._wait(lambda: sock.exists(), "munged did not create its socket")
            self._spawn(["slurmctld", "-D", "-i", "-f", str(self.conf)], env, d / "slurmctld.out")
            self._spawn(["slurmd", "-D", "-f", str(self.conf), "-N", host], env, d / "slurmd.out")
            self._wait(self._node_idle, "the node did not become idle")
        except BaseException:
            self.stop()
            raise
        return self

    def _spawn(self, cmd: list[str], env: dict, log: Path) -> None:
        with open(log, "wb") as f:
            self.procs.append(subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT,
                                               stdin=subprocess.DEVNULL, start_new_session=True))

    def _wait(self, ok, what: str) -> None:
        t_end = time.monotonic() + self.timeout
        while time.monotonic() < t_end:
            dead = [p for p in self.procs if p.poll() is not None]
            if dead:
                raise Unavailable(f"{Path(dead[0].args[0]).name} exited with code {dead[0].returncode} "
                                  f"({self._log_tail(dead[0])})")
            if ok():
                return
            time.sleep(0.3)
        raise Unavailable(f"{what} within {self.timeout:.0f} s ({self._log_tail(self.procs[-1])})")

    def _log_tail(self, p: subprocess.Popen) -> str:
        name = Path(p.args[0]).name
        for f in (self.dir / f"{name}.log", self.dir / f"{name}.out", self.dir / "munge" / f"{name}.log"):
            if f.is_file() and f.read_text(errors="replace").strip():
                return f"{f}: " + f.read_text(errors="replace").strip().splitlines()[-1]
        return "no log"

    def _node_idle(self) -> bool:
        r = self.run("sinfo", "-h", "-N", "-o", "%T", check=False)
        return r.returncode == 0 and r.stdout.strip() == "idle"

    # -------------------------------------------------------------- use
    def run(self, *cmd: str, check: bool = True) -> subprocess.CompletedProcess:
        """A Slurm client command against this cluster."""
        return subprocess.run(list(cmd), env=dict(os.environ, **self.env), capture_output=True, text=True,
                              timeout=30, check=check)

    def jobs(self) -> list[str]:
        """IDs of jobs pending or running on this cluster."""
        r = self.run("squeue", "-h", "-o", "%i", check=False)
        return r.stdout.split() if r.returncode == 0 else []

    def wait_no_jobs(self, timeout: float = 30.0) -> list[str]:
        """Wait until no job is queued or running; the IDs still there at the timeout."""
        t_end = time.monotonic() + timeout
        while (left := self.jobs()) and time.monotonic() < t_end:
            time.sleep(0.5)
        return left

    # -------------------------------------------------------------- stop
    def stop(self) -> None:
        """Cancel this cluster's jobs, then end the daemons we started (by PID), newest first."""
        if self.procs and all(p.poll() is None for p in self.procs):
            if self.jobs():
                self.run("scancel", "--full", "--state=PENDING", check=False)
                self.run("scancel", "--full", check=False)
                self.wait_no_jobs(15)
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in reversed(self.procs):
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        self.procs = []
        if self.dir is not None:
            shutil.rmtree(self.dir, ignore_errors=True)
            self.dir = None
