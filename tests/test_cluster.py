"""The study on a Dask cluster (issue 17, part 6): a real scheduler and two workers as
processes on localhost run a small study; its runs.csv is the local pool's, to the last digit
in every column but the timings, and a worker killed mid-run costs that run only, which
another worker runs again."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rovergate.session import free_loopback_port

ROVERGATE = [sys.executable, "-m", "mission.cli"]
STUDY = ["--scenes", "arch_field", "--starts", "a", "--conditions", "obs", "learned",
         "--reps", "2", "--filter-reps", "2", "--steps", "6", "--no-progress"]


def _dask(*args: str) -> subprocess.Popen:
    exe = Path(sys.executable).with_name("dask")
    return subprocess.Popen([str(exe), *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _rows(path: Path) -> list[dict]:
    """runs.csv without its timing and cost columns (seconds, peak memory, compute energy),
    by run."""
    with open(path) as f:
        rows = list(csv.DictReader(f))
    keep = [k for k in rows[0] if not k.endswith("_s")
            and k not in ("peak_rss_mb", "energy_compute_kj")]
    return sorted(({k: r[k] for k in keep} for r in rows),
                  key=lambda r: (r["condition"], r["rep"]))


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)


@pytest.mark.e2e
def test_a_study_on_a_cluster_writes_the_local_pools_runs_even_when_a_worker_dies(
        tmp_path: Path):
    from distributed import Client
    port = free_loopback_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = _dask("scheduler", "--host", "127.0.0.1", "--port", str(port),
                      "--no-dashboard")
    workers = [_dask("worker", address, "--nthreads", "1", "--no-dashboard", "--name",
                     f"w{i}") for i in range(2)]
    try:
        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
            study = subprocess.Popen([*ROVERGATE, "study", "--cluster", address, "--out",
                                      str(tmp_path / "cluster"), *STUDY],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            # Kill the machine of a worker while it runs a mission (nanny and worker both).
            deadline = time.monotonic() + 120
            busy = None
            while busy is None and time.monotonic() < deadline:
                processing = client.processing()
                busy = next((w for w, tasks in processing.items() if tasks), None)
                if busy is None:
                    time.sleep(0.1)  # polling the scheduler's state, not waiting on a clock
            assert busy is not None, "no worker took a run within 120 s"
            assert all(str(k).startswith("rovergate-") for k in processing[busy])
            name = client.scheduler_info()["workers"][busy]["name"]
            victim = workers[int(str(name)[1:])]
            _stop(victim)
            out, err = study.communicate(timeout=600)
        assert study.returncode == 0, err[-3000:]
        local = subprocess.run([*ROVERGATE, "study", "--workers", "2", "--out",
                                str(tmp_path / "local"), *STUDY], capture_output=True,
                               text=True, timeout=600)
        assert local.returncode == 0, local.stderr[-3000:]
    finally:
        for p in (*workers, scheduler):
            _stop(p)
    cluster_rows = _rows(tmp_path / "cluster" / "runs.csv")
    assert len(cluster_rows) == 4
    assert cluster_rows == _rows(tmp_path / "local" / "runs.csv")
    for run in (tmp_path / "local" / "runs").iterdir():
        there = tmp_path / "cluster" / "runs" / run.name
        assert (there / "coverage.csv").read_bytes() == (run / "coverage.csv").read_bytes()
        assert (there / "config.json").read_text().replace(
            str(tmp_path / "cluster"), str(tmp_path / "local")) == \
            (run / "config.json").read_text()


@pytest.mark.parametrize("address, says", [("scheduler-host", "give the scheduler's address"),
                                            (None, "no Dask scheduler answered")])
def test_a_cluster_that_cannot_be_used_is_one_line(monkeypatch, address, says):
    from mission.study import cluster
    from rovergate.errors import ConfigError
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 2)
    address = address or f"tcp://127.0.0.1:{free_loopback_port()}"  # nothing listens there
    with pytest.raises(ConfigError, match=says) as err:
        list(cluster.cluster_results(address, [], 1, Path("unused")))
    assert "\n" not in str(err.value)
