"""The GPU visit script (benchmarks/gpu_visit.sh, issue 45 item 3) runs only the phases asked for and never
past its budget: a session has 15 device-minutes, so a visit that overruns or runs the wrong phases is lost.
Run here on the CPU with no wheelhouse (its install phase fails, as it may; the next phases still run)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _visit(tmp_path: Path, **env) -> list[list[str]]:
    out = tmp_path / "out"
    e = {**{k: v for k, v in os.environ.items() if k != "PHASES"}, "OUT": str(out), "WORK": str(tmp_path / "work"),
         "WHL": str(tmp_path / "no-wheels"), "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", **env}
    r = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_visit.sh")], env=e, capture_output=True,
                       text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-2000:]
    return [line.split("\t") for line in (out / "phases.tsv").read_text().splitlines()]


def test_without_phases_every_phase_is_tried_and_a_spent_budget_skips_them(tmp_path):
    """No PHASES: all of them (the default); with 20 s of budget every one is skipped, none runs."""
    rows = _visit(tmp_path, BUDGET_S="20")
    phases = [r for r in rows if not r[0].startswith(("gpu-busy:", "throughput:"))]  # the phases' own rows
    names = {r[0] for r in phases}
    assert {"install", "probe", "pytest", "gpu_check", "render:pt-w1:w1:shards4", "fit"} <= names, names
    assert not any(n.startswith("render:steady") for n in names)  # only with STEADY_S
    assert all(r[1] == "skip" for r in phases), phases


def test_only_the_phases_asked_for_run(tmp_path):
    rows = _visit(tmp_path, PHASES="none", BUDGET_S="300")
    assert [r[0] for r in rows] == ["install", "probe"]  # nothing of pytest, renders, training or fit
    assert rows[0][1] != "0"  # no wheels to install: it fails, and the visit goes on
    assert rows[1][1] == "0"


def test_no_phase_runs_past_the_budget(tmp_path):
    # 40 s of budget: every phase that starts is cut to end 10 s before it (the renders' own timeouts are
    # 45 s), the later renders find under 30 s left and are skipped, and so is fit (it needs >= 130 s)
    rows = _visit(tmp_path, PHASES="render,fit", BUDGET_S="40")
    log = (tmp_path / "out" / "log.txt").read_text()
    started = [line for line in log.splitlines() if line.startswith("=== ") and "timeout" in line]
    for line in started:  # "=== NAME (timeout Ts, Ls left) HH:MM:SS"
        t, l = line.split("(timeout ")[1].split("s, ")[:2]
        assert int(t) <= int(l.split("s left")[0]) - 10, line
    skipped = {r[0] for r in rows if r[1] == "skip"}
    assert "fit" in skipped and any(n.startswith("render:") for n in skipped)
    assert int(log.rsplit("total ", 1)[1].split()[0]) <= 40 + 5  # the visit's own wall time
    assert not any(r[0].startswith(("train", "steady", "pytest", "gpu_check")) for r in rows)


def test_a_misspelt_phase_is_one_line_before_any_work(tmp_path):
    """`PHASES=stedy` would otherwise run install and probe, then nothing: a visit lost.  One line naming the
    phase and the known ones, exit 1, no output folder made."""
    e = {**os.environ, "OUT": str(tmp_path / "out"), "WORK": str(tmp_path / "work"), "PHASES": "steady,stedy"}
    r = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_visit.sh")], env=e, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [
        "error: PHASES: unknown phase 'stedy' (known: pytest,bench-train,gpu_check,render,steady,corpora,"
        "breakdown,thr,fit,none)"]
    assert not (tmp_path / "out").exists() and not (tmp_path / "work").exists()
