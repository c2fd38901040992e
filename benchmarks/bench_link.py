"""Benchmark: the downlink queue's throughput, and how fast the loop recovers from a death.

Queue: stores, radiates and acknowledges telemetry items of the mission's real sizes (a
MissionStatus, a PoseStamped, a 20 000-point map snapshot) in a SQLite file, several rounds,
and prints median items/s and MB/s.

Recovery (``--recovery``): runs a 12-step process-set mission per round, SIGKILLs each module
once (sim at step 2, planner 4, mapper 6, gate 8; the mapper runs the learned model under the
gated condition), and prints the median time from each death to the module's liveliness token
and to the loop resuming (the module's first output again).

Resume (``--resume``): SIGKILLs the mission manager of a 20-step gated mission at step 10, and
prints the median time from ``rovergate run --out OUT --resume`` to the loop running again
and to the mission's end, and whether the coverage matched an uninterrupted run's.

Usage: .venv/bin/python benchmarks/bench_link.py [--rounds 5] [--recovery] [--resume]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from mission.link.downlink import DownlinkQueue
from rovergate.messages import encode_item
from rovergate.types import SURFACE_DTYPE, MissionStatus, Pose


def bench_queue(tmp: Path, rounds: int) -> None:
    status = encode_item("status", MissionStatus(42, 100, "running", "gated", 0.5, 0))
    pose = encode_item("pose", (42, Pose.from_xyz_yaw(1.0, 2.0, 0.3, 0.5)))
    cloud = np.zeros(20_000, dtype=SURFACE_DTYPE)
    cloud["x"] = np.random.default_rng(0).uniform(-20, 20, len(cloud))
    snapshot = encode_item("map", (42, cloud))
    cases = {"status": ("status", status, 2000), "pose": ("pose", pose, 2000),
             "map": ("map", snapshot, 50)}
    print(f"item sizes: status {len(status[1])} B, pose {len(pose[1])} B, "
          f"map {len(snapshot[1]) / 1e3:.0f} kB")
    print(f"{'kind':8} {'put items/s':>12} {'put MB/s':>9} {'take+ack items/s':>17} "
          f"{'take+ack MB/s':>14}")
    for name, (kind, (msgtype, payload), n) in cases.items():
        put_rates, drain_rates = [], []
        for r in range(rounds):
            q = DownlinkQueue(tmp / f"{name}-{r}.sqlite", max_bytes=2**34)
            t0 = time.perf_counter()
            for i in range(n):
                # Maps supersede each other: put them as events would be kept, to time writes.
                q.put("event" if kind == "map" else kind, msgtype, i, payload)
            put_rates.append(n / (time.perf_counter() - t0))
            t0 = time.perf_counter()
            taken = 0
            while taken < n:
                items = q.take(8 * 2**20, 0.0, 1e9)
                q.ack([i.seq for i in items])
                taken += len(items)
            drain_rates.append(n / (time.perf_counter() - t0))
            q.close()
        put, drain = statistics.median(put_rates), statistics.median(drain_rates)
        mb = len(payload) / 1e6
        print(f"{name:8} {put:12.0f} {put * mb:9.1f} {drain:17.0f} {drain * mb:14.1f}")


def bench_recovery(tmp: Path, rounds: int) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from conftest import StatusWatcher

    from rovergate.session import free_loopback_port
    kills = {2: "sim", 4: "planner", 6: "mapper", 8: "gate"}
    ready: dict[str, list[float]] = {m: [] for m in kills.values()}
    resumed: dict[str, list[float]] = {m: [] for m in kills.values()}
    for r in range(rounds):
        port = free_loopback_port()
        out = tmp / f"mission-{r}"
        proc = subprocess.Popen(
            [sys.executable, "-m", "mission.cli", "run", "--steps", "12", "--condition",
             "gated", "--no-progress", "--out", str(out), "--listen", f"tcp/127.0.0.1:{port}",
             "--contact.no-enabled"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            text=True)
        lines: list[str] = []
        started = threading.Event()

        def read(p=proc, ls=lines, ev=started) -> None:
            for line in p.stderr:
                ls.append(line)
                if "started sim" in line:  # the mission's session listens by then
                    ev.set()
        threading.Thread(target=read, daemon=True).start()
        started.wait(120)
        watcher = StatusWatcher(port)
        try:
            for step, name in kills.items():
                watcher.wait_step(step, 300)
                pid = [int(m.group(1)) for line in list(lines)
                       if (m := re.search(rf"started {name} \(pid (\d+)\)", line))][-1]
                os.kill(pid, signal.SIGKILL)
            proc.wait(600)
        finally:
            # Closed on this thread, whatever happened: a Zenoh session closed by a thread
            # that outlives main() aborts the interpreter at exit ("FATAL: exception not
            # rethrown", exit 134; an earlier version closed it in a daemon thread).
            watcher.close()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        metrics = json.loads((out / "metrics.json").read_text())
        for e in metrics["restarts"]:
            ready[e["module"]].append(e["death_to_ready_s"])
            resumed[e["module"]].append(e["death_to_resume_s"])
    print(f"{'module':8} {'death to token s':>17} {'death to loop resumed s':>24}  (medians of "
          f"{rounds})")
    for m in kills.values():
        print(f"{m:8} {statistics.median(ready[m]):17.2f} {statistics.median(resumed[m]):24.2f}")


def bench_resume(tmp: Path, rounds: int) -> None:
    """SIGKILL the mission manager of a 20-step gated mission at step 10; time
    ``rovergate run --out OUT --resume`` to the loop running again, and check the coverage
    against an uninterrupted mission's."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from conftest import RovergateProcess, StatusWatcher, wait_gone

    from rovergate.session import free_loopback_port
    base = ["--steps", "20", "--condition", "gated", "--no-progress", "--contact.no-enabled"]
    clean = tmp / "resume-clean"
    subprocess.run([sys.executable, "-m", "mission.cli", "run", *base, "--out", str(clean)],
                   check=True, capture_output=True, timeout=600)
    to_loop, to_end, same = [], [], []
    for r in range(rounds):
        port, out = free_loopback_port(), tmp / f"resume-{r}"
        first = RovergateProcess(["run", *base, "--out", str(out),
                                  "--listen", f"tcp/127.0.0.1:{port}"])
        pids = [first.pid(m) for m in ("sim", "mapper", "gate", "planner")]
        watcher = StatusWatcher(port)
        try:
            watcher.wait_step(10, 300)
            os.kill(first.proc.pid, signal.SIGKILL)
        finally:
            watcher.close()
        first.finish(60)
        for pid in pids:
            wait_gone(pid, 60)
        t0 = time.perf_counter()
        resumed = RovergateProcess(["run", "--out", str(out), "--resume", "--no-progress"])
        resumed.wait_for_line(r"resumed at step \d+", 300)
        to_loop.append(time.perf_counter() - t0)
        if resumed.finish(600) != 0:
            raise SystemExit(f"the resumed mission failed:\n{resumed.text[-3000:]}")
        to_end.append(time.perf_counter() - t0)
        same.append((out / "coverage.csv").read_text() == (clean / "coverage.csv").read_text())
    print(f"mission manager SIGKILLed at step 10 of 20 (gated), {rounds} rounds: "
          f"`--resume` start to the loop running {statistics.median(to_loop):.2f} s, "
          f"to the end of the mission {statistics.median(to_end):.2f} s (medians); per-step "
          f"coverage identical to an uninterrupted run's in {sum(same)} of {rounds}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--recovery", action="store_true", help="also time module recovery")
    ap.add_argument("--resume", action="store_true",
                    help="also time a mission manager's resume after SIGKILL")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="rovergate-bench-link-"))
    bench_queue(tmp, args.rounds)
    if args.recovery:
        bench_recovery(tmp, min(args.rounds, 3))
    if args.resume:
        bench_resume(tmp, min(args.rounds, 3))


if __name__ == "__main__":
    main()
