"""``rovergate study``: the paper's controlled study, every run closed loop from scratch.

Each (scene, start, condition, repetition) is one mission of ``--steps`` planning steps, run in
one process (:func:`mission.loop.run_in_process`, which gives the same numbers as the process
set) by a pool of worker processes, one torch thread each. Repetition r runs with seed r, so
repetitions differ in the planner's candidate draws and OMPL's sampling, and the same seed
gives the same run in any worker.

Layout of ``--out``::

    study.json          the study's settings (a re-run must match them)
    runs/<id>/          one finished run: metrics.json, coverage.csv, config.json
    runs.csv            one row per finished run
    table1.md           the paper's Table 1 layout over every repetition, bootstrap 95% CIs over
                        starts, a placebo row (learned against itself), failure modes
    table2.md           the paper's Table 2 layout: learned against gated, every start, with
                        sign-flip p-values, Holm correction, a sign test, the paper's selection
    summary.json        the tables' figures, the study's wall time and per-stage medians
    coverage_<condition>.png  every run's coverage curve, with the mean
    coverage_curves.csv every run's per-step coverage, one row per run

A study of cells (``--platform flyer rover``, ``--profiles ...``, or ``--preset validation``)
runs every (platform, sensing profile) as a cell: run ids start with ``<platform>-<profile>-``,
each cell's tables (the layout above, without study.json) go to ``<platform>-<profile>/``, and
the study's own outputs are :mod:`mission.validation`'s: runs.csv over every cell,
validation.md, validation_*.png and summary.json.

Resuming: a run directory appears only complete (it is written under a temporary name and
renamed), so a re-run with the same ``--out`` skips every finished run, and a killed study
loses at most the runs that were in flight.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from rover_sim.catalog import START_NAMES, SUITE, load_scene, resolve_scene
from rovergate.conditions import get_condition
from rovergate.config import MissionConfig, from_dict, to_dict
from rovergate.errors import ConfigError
from rovergate.logs import init_logging

log = logging.getLogger("rovergate.study")

#: The paper's order of planner-facing conditions, then the filter.
PAPER_ORDER = ("obs", "learned-fp", "learned", "learned+fn", "truth", "gated")


@dataclass
class StudyConfig:
    """The controlled study (paper, Section 4) and its extension to every start."""

    scenes: tuple[str, ...] = SUITE
    """Scenes: suite names or mesh files (`rovergate scenes` lists the suite)."""
    starts: tuple[str, ...] = START_NAMES
    """Named starts of every scene."""
    conditions: tuple[str, ...] = PAPER_ORDER
    """Planner-facing conditions (`learned` is the baseline of every delta and of S70, so it
    is always run)."""
    reps: int = 3
    """Repetitions of every condition (repetition r runs with seed r): three at least, so
    that the placebo row (learned against itself) shows the noise floor."""
    filter_reps: int = 3
    """Repetitions of `learned` and `gated` on every start, for Table 2 (at least --reps)."""
    steps: int = 100
    """Planning steps per run (T; each run records T + 1 coverage values)."""
    platform: tuple[str, ...] = ("flyer",)
    """Platforms: the paper's setting is the free-flying camera; `rover` is the extension.
    With more than one, or with --profiles, every (platform, profile) is a cell of its own
    (see the module docstring)."""
    profiles: tuple[str, ...] = ("nominal",)
    """Sensing profiles: nominal, degraded, drift, drift+degraded (SENSING_PROFILES; levels
    in the README). `nominal` runs the --mission.sensing settings as given; the others set
    the fields they name over them."""
    preset: str = ""
    """A named design (PRESETS): `validation` is the paper's required validation (issue 16).
    On the command line it stands for its flags, placed before the ones given: a flag given
    wins over the preset's. In Python, build it with :func:`preset_config`."""
    workers: int = 0
    """Worker processes (0: one per CPU core). Each runs one mission at a time."""
    cluster: str = ""
    """Run on a Dask distributed cluster instead of local workers: the scheduler's address,
    e.g. tcp://10.0.0.5:8786 (`dask scheduler` prints it; start `dask worker ADDRESS
    --nthreads 1` on each machine, with rovergate installed). Same runs, same runs.csv, same
    resumption; see mission/cluster.py and the README."""
    torch_threads: int = 1
    """Torch threads per worker."""
    out: Path = Path("runs/study")
    """Directory of the study (see the module docstring); re-running resumes it."""
    bootstrap: int = 10_000
    """Paired bootstrap resamples for the confidence intervals."""
    progress: bool = True
    """Show a progress bar with an ETA."""
    record: bool = False
    """Record every run's messages into OUT/runs/<id>/bag (`rovergate replay` plays one).
    Off by default: a bag holds about 150 MB per 100 steps (README, "The flight recorder and
    replay"), which over a study's hundreds of runs is tens of GB."""
    mission: MissionConfig = field(default_factory=MissionConfig)
    """Every other mission setting (sensing, planner, gate, ...), as `rovergate run` takes
    them. The study sets the scene, start, condition, seed, steps, platform, out, in-process
    and progress of every run, and refuses those --mission flags (see OWNED_MISSION_FLAGS)."""


class StudyFlagError(ConfigError):
    """A --mission flag for a setting the study makes itself (the message names the study's
    flag to use instead)."""


OWNED_MISSION_FLAGS: dict[str, str] = {
    "platform": "use --platform {value}",
    "steps": "use --steps {value}",
    "scene": "use --scenes {value}",
    "scene.name": "use --scenes {value}",
    "scene.d-scene-m": "the study takes it from each scene; leave it out",
    "scene.bounds-m": "the study takes it from each scene; leave it out",
    "start": "use --starts {value}",
    "condition": "use --conditions {value}",
    "seed": "repetition r runs with seed r; use --reps N for more seeds",
    "out": "use --out {value} (each run goes to OUT/runs/<id>)",
    "in-process": "every run is in process; leave it out",
    "progress": "use --progress or --no-progress (the study's progress bar)",
    "record": "use --record (the study's runs are not recorded unless it is given)",
    "viz": "a study's runs are not served live; record them (--record) and watch one with "
           "`rovergate replay OUT/runs/<id>/bag --viz`",
    "ros2": "a study's runs are not published live; record them (--record) and publish one "
            "with `rovergate replay OUT/runs/<id>/bag --ros2`",
}
"""The --mission flags (after ``--mission.``) of what :func:`mission_config` sets for every
run, and what to do instead; ``{value}`` is the value given (VALUE if none)."""

#: The conditions of the validation study: the baseline, the paper's gate and its variants.
VALIDATION_CONDITIONS = ("learned", "gated", "gated-ray", "gated-pose", "gated-split")

#: Sensing profiles: SensingConfig fields each sets over the --mission.sensing settings.
#: Degraded: 10% of every image lost in blobs (structured dropout), 1% range noise, returns
#: lost beyond 80 degrees of incidence. Drift: a random walk on the published pose of 0.02 m
#: (x, y) and 0.01 m (z) and 0.3 degrees of heading per step (after 100 steps: 0.2 m, 0.1 m,
#: 3 degrees standard deviation).
DEGRADED = {"dropout_blob_frac": 0.1, "noise_frac": 0.01, "grazing_max_deg": 80.0}
DRIFT = {"drift_xy_m": 0.02, "drift_z_m": 0.01, "drift_yaw_deg": 0.3}
SENSING_PROFILES: dict[str, dict] = {
    "nominal": {}, "degraded": DEGRADED, "drift": DRIFT, "drift+degraded": {**DRIFT, **DEGRADED},
}

#: Named designs: the StudyConfig fields each sets (see :func:`preset_args`).
PRESETS: dict[str, dict] = {
    # The paper's validation list (issue 16): 6 scenes x start a x 5 conditions x 4 profiles x
    # 2 platforms x 2 repetitions = 480 runs of 100 steps, about an hour on 2 cores. It leaves
    # out starts b to e (the unit of every interval is the scene) and a third repetition.
    "validation": {"scenes": SUITE, "starts": ("a",), "conditions": VALIDATION_CONDITIONS,
                   "platform": ("flyer", "rover"), "profiles": tuple(SENSING_PROFILES),
                   "reps": 2, "filter_reps": 2, "steps": 100},
}

#: Sections and flags that only the process set reads: every study run is in one process, so
#: they would have no effect.
PROCESS_SET_ONLY: tuple[str, ...] = (
    "contact", "planner.command", "planner.programs", "ready-timeout-s", "step-timeout-s",
    "max-restarts", "resume", "mode", "connect", "listen", "namespace", "multicast-scouting",
    "wait-for-peers")


def refuse_owned_mission_flags(argv: list[str]) -> None:
    """Raise :class:`StudyFlagError` on the first ``--mission.X`` flag in ``argv`` (the
    study's arguments) for a setting the study makes itself, which would otherwise be
    accepted and silently overridden. It reads argv: a parsed config cannot tell a flag given
    from a default."""
    for i, arg in enumerate(argv):
        if not arg.startswith("--mission."):
            continue
        flag, eq, value = arg.partition("=")
        name = flag.removeprefix("--mission.").replace("_", "-")
        section, dot, last = name.rpartition(".")
        if last.startswith("no-"):  # the negative of a boolean flag: --mission.no-progress
            name = section + dot + last.removeprefix("no-")
        if any(name == p or name.startswith(p + ".") for p in PROCESS_SET_ONLY):
            raise StudyFlagError(f"{flag} has no effect on a study: every run is in one "
                                 "process, and only the process set reads it; leave it out")
        hint = OWNED_MISSION_FLAGS.get(name)
        if hint is None:
            continue
        if not eq:
            value = argv[i + 1] if i + 1 < len(argv) and not argv[i + 1].startswith("--") \
                else ""
        raise StudyFlagError(f"{flag} is set by the study for every run; "
                             + hint.format(value=value or "VALUE"))


@dataclass(frozen=True)
class RunSpec:
    scene: str
    start: str
    condition: str
    rep: int
    platform: str = ""
    """Set in a study of cells (several platforms or profiles); empty: the study's one."""
    profile: str = ""

    @property
    def id(self) -> str:
        scene = Path(self.scene).stem if "/" in self.scene or "." in self.scene else self.scene
        cell = f"{self.platform}-{self.profile}-" if self.platform else ""
        return f"{cell}{scene}-{self.start}-{self.condition}-r{self.rep}"

    @property
    def cell(self) -> str:
        """The (platform, profile) cell's name, its directory in the study."""
        return f"{self.platform}-{self.profile}"


def _names(value: str | tuple[str, ...]) -> tuple[str, ...]:
    """A name or names, as a tuple without repeats (``platform="rover"`` is one platform)."""
    return (value,) if isinstance(value, str) else tuple(dict.fromkeys(value))


def cells(cfg: StudyConfig) -> list[tuple[str, str]]:
    """The study's (platform, profile) cells; empty for a study of one platform, nominal."""
    platforms, profiles = _names(cfg.platform), _names(cfg.profiles)
    if len(platforms) == 1 and profiles == ("nominal",):
        return []
    return [(p, s) for p in platforms for s in profiles]


def _check_preset(name: str) -> dict:
    if name not in PRESETS:
        raise ConfigError(f"--preset {name!r} is not a preset; the presets are "
                          + ", ".join(PRESETS))
    return PRESETS[name]


def preset_args(argv: list[str]) -> list[str]:
    """The study's arguments with the preset's flags placed before them: the last value of a
    flag wins, so every flag given overrides the preset's."""
    name = None
    for i, arg in enumerate(argv):
        if arg == "--preset" and i + 1 < len(argv):
            name = argv[i + 1]
        elif arg.startswith("--preset="):
            name = arg.partition("=")[2]
    if not name:
        return argv
    flags = []
    for key, value in _check_preset(name).items():
        flags.append("--" + key.replace("_", "-"))
        flags += [str(v) for v in value] if isinstance(value, tuple) else [str(value)]
    return flags + argv


def preset_config(name: str, **settings) -> StudyConfig:
    """A preset's StudyConfig, with ``settings`` over it (the API's --preset)."""
    return StudyConfig(**{**_check_preset(name), "preset": name, **settings})


def check_study(cfg: StudyConfig) -> StudyConfig:
    """Validate the settings; one line for each kind of mistake. Returns them resolved."""
    if cfg.preset:
        preset = _check_preset(cfg.preset)
        default = StudyConfig()
        if all(getattr(cfg, k) == getattr(default, k) for k in preset):
            raise ConfigError(f"StudyConfig(preset={cfg.preset!r}) alone sets nothing; build "
                              f"it with mission.study.preset_config({cfg.preset!r}, ...)")
    cfg = replace(cfg, platform=_names(cfg.platform), profiles=_names(cfg.profiles))
    if not cfg.platform or not cfg.profiles:
        raise ConfigError("--platform and --profiles each need at least one value")
    for p in cfg.profiles:
        if p not in SENSING_PROFILES:
            raise ConfigError(f"--profiles: {p!r} is not a sensing profile; the profiles are "
                              + ", ".join(SENSING_PROFILES))
    if not cfg.scenes or not cfg.starts or not cfg.conditions:
        raise ConfigError("--scenes, --starts and --conditions each need at least one "
                          "value")
    for c in cfg.conditions:
        get_condition(c)
    conditions = tuple(dict.fromkeys(("learned", *cfg.conditions)))  # the baseline first
    conditions = tuple(c for c in PAPER_ORDER if c in conditions) + tuple(
        c for c in conditions if c not in PAPER_ORDER)
    if cfg.reps < 1 or cfg.filter_reps < 0 or cfg.steps < 1:
        raise ConfigError(f"--reps and --steps must be at least 1 and --filter-reps at "
                          f"least 0; got {cfg.reps}, {cfg.steps}, {cfg.filter_reps}")
    for name in cfg.scenes:
        scene = load_scene(replace(cfg.mission.scene, name=name, d_scene_m=0.0,
                                   bounds_m=(0,) * 6))
        for s in cfg.starts:
            if s not in scene.starts:
                raise ConfigError(f"scene {name!r} has no start {s!r}; its starts are "
                                  f"{', '.join(scene.starts)}")
    # Every other setting as the runs get it (platform, planner, checkpoint, counts and
    # ranges): refused here, not once per run by the workers. Runs differ only by condition,
    # and conditions only by whether they run the model: one check of each kind.
    from mission.run import check_runnable
    kinds = {get_condition(c).needs_prediction: c for c in reversed(conditions)}
    for c in kinds.values():
        for platform in cfg.platform:
            for profile in cfg.profiles:
                check_runnable(mission_config(
                    cfg, RunSpec(cfg.scenes[0], cfg.starts[0], c, 0, platform, profile),
                    Path(cfg.out)))
    workers = cfg.workers or os.cpu_count() or 1
    return replace(cfg, conditions=conditions, workers=workers)


def run_specs(cfg: StudyConfig) -> list[RunSpec]:
    """Every run of the study, in a fixed order."""
    specs = []
    for platform, profile in cells(cfg) or [("", "")]:
        for scene in cfg.scenes:
            for start in cfg.starts:
                for condition in cfg.conditions:
                    reps = cfg.reps
                    if condition == "learned" or get_condition(condition).withholds:
                        reps = max(reps, cfg.filter_reps)
                    specs.extend(RunSpec(scene, start, condition, r, platform, profile)
                                 for r in range(reps))
    return specs


def mission_config(cfg: StudyConfig, spec: RunSpec, run_dir: Path) -> MissionConfig:
    m = from_dict(MissionConfig, to_dict(cfg.mission))  # a deep copy
    m.scene = replace(m.scene, name=spec.scene, d_scene_m=0.0, bounds_m=(0,) * 6)
    m.start, m.condition, m.seed, m.steps = spec.start, spec.condition, spec.rep, cfg.steps
    m.platform, m.out, m.in_process, m.progress = (spec.platform or _names(cfg.platform)[0],
                                                   run_dir, True, False)
    m.record, m.viz, m.ros2 = cfg.record, False, False
    if spec.profile:
        m.sensing = replace(m.sensing, **SENSING_PROFILES[spec.profile])
    return m


# ----------------------------------------------------------------------------- workers

def _init_worker(threads: int) -> None:
    import torch

    from rovergate.runtime import tune_allocator
    tune_allocator()
    torch.set_num_threads(threads)
    logging.getLogger().setLevel(logging.WARNING)  # the study's log is the progress bar


def _run_one(job: tuple[dict, str, str]) -> tuple[str, float, str | None]:
    """Run one mission into a temporary directory and rename it into place when complete."""
    from mission.loop import run_in_process
    from mission.report import write_report
    from rovergate.config import save_config
    mission, run_id, runs_dir = job
    cfg = from_dict(MissionConfig, mission)
    final = Path(runs_dir) / run_id
    tmp = Path(runs_dir) / f".{run_id}.tmp-{os.getpid()}"
    t0 = time.perf_counter()
    try:
        resolve_scene(cfg.scene)
        cfg.out = tmp
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        record = run_in_process(cfg)
        cfg.out = final
        if record.recording:  # the bag moves with the run's directory
            record.recording["path"] = str(final / Path(record.recording["path"]).name)
        save_config(cfg, tmp / "config.json")
        write_report(cfg, record, tmp, plots=False)
        os.replace(tmp, final)
    except Exception as exc:  # a failed run is reported, and the study goes on
        shutil.rmtree(tmp, ignore_errors=True)
        return run_id, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}"
    return run_id, time.perf_counter() - t0, None


# ----------------------------------------------------------------------------- the study

def _settings(cfg: StudyConfig) -> dict:
    """What must match for a study directory to be resumed."""
    d = to_dict(cfg)
    for k in ("workers", "torch_threads", "out", "bootstrap", "progress", "preset", "record",
              "cluster"):
        d.pop(k)
    d["mission"] = _without_recording(d["mission"])
    # A study of one platform, nominal, saves its settings as studies did before cells.
    if not cells(cfg):
        d["platform"] = cfg.platform[0]
        d.pop("profiles")
    return d


def _normalised(saved: dict | None) -> dict | None:
    """Saved settings with the mission's settings that did not exist when they were saved
    filled in at their defaults (what those runs ran with), so that a study resumes across a
    release that added a setting."""
    if not isinstance(saved, dict) or not isinstance(saved.get("mission"), dict):
        return saved
    try:
        mission = to_dict(from_dict(MissionConfig, saved["mission"]))
    except Exception:  # not ours to judge here: it simply does not match
        return saved
    return {**saved, "mission": _without_recording(mission)}


#: Mission settings that change what is written or served beside a run, never its figures.
_OUTPUTS = ("record", "record_compression", "viz", "viz_host", "viz_port", "ros2",
            "ros2_router", "ros2_domain")


def _without_recording(mission: dict) -> dict:
    return {k: v for k, v in mission.items() if k not in _OUTPUTS}


def _results(cfg: StudyConfig, jobs: list, runs_dir: Path):
    """(run id, seconds, error) of every job as it finishes: from a local pool of
    ``cfg.workers`` processes, or from the Dask cluster at ``cfg.cluster``."""
    if cfg.cluster:
        from mission.cluster import cluster_results
        yield from cluster_results(cfg.cluster, jobs, cfg.torch_threads, runs_dir)
        return
    ctx = mp.get_context("spawn")
    with ctx.Pool(cfg.workers, initializer=_init_worker,
                  initargs=(cfg.torch_threads,)) as pool:
        yield from pool.imap_unordered(_run_one, jobs)


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt  # leaving the pool's context terminates its workers


def main(cfg: StudyConfig) -> int:
    init_logging("study")
    signal.signal(signal.SIGTERM, _terminate)
    cfg = check_study(cfg)
    out = Path(cfg.out)
    runs_dir = out / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    settings_path = out / "study.json"
    settings = _settings(cfg)
    if settings_path.exists():
        try:
            saved = json.loads(settings_path.read_text())
        except ValueError:
            raise ConfigError(f"{settings_path} is not valid JSON; delete it, or give "
                              "--out a new directory") from None
        if _normalised(saved.get("settings")) != settings:
            raise ConfigError(f"{out} holds a study with other settings; give --out a "
                              f"new directory, or delete {out} to start this one there")
        sessions = saved.get("sessions", [])
    else:
        sessions = []
    for leftover in runs_dir.glob(".*.tmp-*"):  # runs that were in flight when killed
        shutil.rmtree(leftover, ignore_errors=True)

    specs = run_specs(cfg)
    done = {p.name for p in runs_dir.iterdir() if (p / "metrics.json").exists()}
    todo = [s for s in specs if s.id not in done]
    log.info("%d runs: %d finished before, %d to run on %s (out: %s)", len(specs),
             len(specs) - len(todo), len(todo),
             f"the Dask cluster at {cfg.cluster}" if cfg.cluster else f"{cfg.workers} workers",
             out)
    t0 = time.perf_counter()
    session = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "runs": 0, "wall_s": 0.0,
               "workers": cfg.workers, **({"cluster": cfg.cluster} if cfg.cluster else {})}
    sessions.append(session)

    def save_progress() -> None:
        # Written whole or not at all: a study killed mid-write must still resume.
        session["wall_s"] = time.perf_counter() - t0
        tmp = settings_path.with_name(f".{settings_path.name}.tmp")
        tmp.write_text(json.dumps({"settings": settings, "sessions": sessions}, indent=1)
                       + "\n")
        os.replace(tmp, settings_path)

    save_progress()
    failures: list[tuple[str, str]] = []
    if todo:
        jobs = [(to_dict(mission_config(cfg, s, runs_dir / s.id)), s.id, str(runs_dir))
                for s in todo]
        bar = tqdm(total=len(specs), initial=len(specs) - len(todo), desc="study", unit="run",
                   disable=not cfg.progress, file=sys.stderr, smoothing=0.05)
        try:
            for run_id, seconds, error in _results(cfg, jobs, runs_dir):
                bar.update(1)
                if error:
                    failures.append((run_id, error))
                    log.error("run %s failed after %.0f s: %s", run_id, seconds, error)
                else:
                    session["runs"] += 1
                    bar.set_postfix_str(f"{run_id} {seconds:.0f}s")
                    log.info("run %s finished in %.0f s", run_id, seconds)
                save_progress()
        except KeyboardInterrupt:
            bar.close()
            save_progress()
            log.error("stopped; the finished runs are kept: re-run the same command to resume")
            return 130
        bar.close()
    save_progress()

    if cells(cfg):
        from mission.validation import write_validation
        summary = write_validation(cfg, specs, out)
    else:
        from mission.tables import write_tables
        summary = write_tables(cfg, specs, out)
    wall = sum(s["wall_s"] for s in sessions)
    log.info("study: %d runs in %.1f min of wall time over %d session(s); tables in %s",
             summary["runs"], wall / 60, len(sessions), out)
    if failures:
        log.error("%d runs failed (re-run the same command to retry them): %s", len(failures),
                  ", ".join(r for r, _ in failures))
        return 1
    return 0
