"""The study on a Dask distributed cluster (``rovergate study --cluster tcp://HOST:8786``).

Each run is one task: a worker runs the mission in a temporary directory of its own
(:func:`mission.study.worker.run_one`, the local pool's function, with the same torch threads) and
returns the run's files as bytes; the study writes them into ``OUT/runs/<id>`` as the local
pool does (complete or not at all). So the workers need no filesystem shared with the study,
and the same settings give the same runs, to the last digit, on a cluster or a local pool;
only the timing and cost columns of runs.csv (seconds, peak memory, compute energy) differ, as
they do between two local runs.

What the workers need: rovergate installed (the same version, ``pip install -e
'.[cluster]'``), one thread each (``dask worker --nthreads 1``: one mission at a time, and
repetition r is seeded r whichever worker runs it). A scene given as a mesh file must exist at
the same path on every worker (a shared or copied directory); the suite's scenes are built
from code. With ``--record``, each run's bag comes back through the scheduler with the rest.

A worker that dies mid-run loses that run only: the scheduler gives the task to another
worker (up to Dask's ``distributed.scheduler.allowed-failures``, 3 by default, after which
the run is reported failed and a re-run of the study retries it).

The scheduler runs whatever a client sends it: keep it on a network only the study's
machines reach, or use Dask's TLS (its ``--tls-*`` options and a ``tls://`` address).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

from rovergate.errors import ConfigError

log = logging.getLogger("rovergate.study")

CONNECT_TIMEOUT_S = 30


def run_remote(job: tuple[dict, str, str], torch_threads: int
               ) -> tuple[str, float, str | None, dict[str, bytes]]:
    """On a worker: run one mission into a temporary directory; its files as bytes."""
    import torch

    from mission.study.worker import run_one
    from rovergate.runtime import tune_allocator
    tune_allocator()
    torch.set_num_threads(torch_threads)  # as the local pool's workers (the worker's log
    # level is the worker's own business)
    mission, run_id, runs_dir = job
    final = str(Path(runs_dir) / run_id)  # where the study keeps it
    with tempfile.TemporaryDirectory(prefix="rovergate-run-") as tmp:
        run_id, seconds, error = run_one((mission, run_id, tmp))
        files: dict[str, bytes] = {}
        if error is None:
            root = Path(tmp) / run_id
            _name_final(root, final)
            for path in sorted(root.rglob("*")):
                if path.is_file():
                    files[str(path.relative_to(root))] = path.read_bytes()
    return run_id, seconds, error, files


def _name_final(root: Path, final: str) -> None:
    """The run's files name the directory the study keeps it in, as a local run's do."""
    config = json.loads((root / "config.json").read_text())
    config["out"] = final
    (root / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    metrics = json.loads((root / "metrics.json").read_text())
    if metrics.get("recording"):
        metrics["recording"]["path"] = str(Path(final) / Path(metrics["recording"]["path"]).name)
        (root / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")


def store_run(runs_dir: Path, run_id: str, files: dict[str, bytes]) -> None:
    """Write a run's files into ``runs_dir/run_id``: under a temporary name, then renamed,
    as the local pool does (a killed study keeps complete runs only)."""
    tmp = runs_dir / f".{run_id}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    for name, data in files.items():
        path = (tmp / name).resolve()
        if tmp.resolve() not in path.parents:  # a worker names files only inside its run
            raise ValueError(f"run {run_id}: a file outside its directory: {name!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    final = runs_dir / run_id
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)


def cluster_results(address: str, jobs: list[tuple[dict, str, str]], torch_threads: int,
                    runs_dir: Path) -> Iterator[tuple[str, float, str | None]]:
    """Run ``jobs`` on the cluster at ``address``, storing each finished run; yields what the
    local pool yields, (run id, seconds, error), as runs finish."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ConfigError("--cluster needs Dask distributed: pip install -e '.[cluster]' "
                          "(`make test` installs it)") from None
    if "://" not in address:
        raise ConfigError(f"--cluster {address!r}: give the scheduler's address, e.g. "
                          "tcp://10.0.0.5:8786 (what `dask scheduler` prints)")
    try:
        client = Client(address, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError) as exc:
        raise ConfigError(f"--cluster: no Dask scheduler answered at {address} within "
                          f"{CONNECT_TIMEOUT_S} s ({exc}); start one with `dask scheduler` "
                          "and workers with `dask worker ADDRESS --nthreads 1`") from None
    try:
        workers = client.scheduler_info().get("workers", {})
        log.info("Dask cluster at %s: %d workers now (%s)", address, len(workers),
                 ", ".join(sorted(w.get("host", "?") for w in workers.values())) or "none yet")
        threaded = sorted(w.get("name", a) for a, w in workers.items() if w.get("nthreads") != 1)
        if threaded:
            raise ConfigError(f"--cluster: workers {', '.join(map(str, threaded))} run more than "
                              "one thread; a worker runs one mission at a time: start it with "
                              "`dask worker ADDRESS --nthreads 1`")
        # Keys of this study alone: Dask shares a key's result between clients, and another
        # study on the cluster may have runs of the same id with other settings.
        study = uuid.uuid4().hex[:12]
        futures = {client.submit(run_remote, job, torch_threads, pure=False,
                                 key=f"rovergate-{study}-{job[1]}"): job[1] for job in jobs}
        try:
            for future in as_completed(futures):
                run_id = futures.pop(future)
                try:
                    run_id, seconds, error, files = future.result()
                except Exception as exc:  # KilledWorker after the allowed failures, ...
                    yield run_id, 0.0, f"{type(exc).__name__}: {exc}"
                    continue
                finally:
                    future.release()  # the run's bytes leave the cluster's memory
                if error is None:
                    try:
                        store_run(runs_dir, run_id, files)
                    except (OSError, ValueError) as exc:
                        error = f"could not store the run: {type(exc).__name__}: {exc}"
                yield run_id, seconds, error
        except BaseException:
            client.cancel(list(futures))
            raise
    finally:
        client.close()
