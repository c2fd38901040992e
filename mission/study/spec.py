"""The study's settings and the runs they expand to: the types every part of the study shares
(:class:`StudyConfig`, :class:`RunSpec`), the sensing profiles and presets, the checks a study's
settings pass before any run starts, and each run's mission configuration."""


from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

from rover_sim.catalog import START_NAMES, SUITE, load_scene
from rovergate.conditions import get_condition
from rovergate.config import MissionConfig, from_dict, to_dict
from rovergate.errors import ConfigError

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
    that the placebo row (learned against itself) shows the noise floor. `learned` and the
    gates run max(--reps, --filter-reps) times."""
    filter_reps: int = 3
    """Repetitions of `learned` and the gates on every start, for Table 2: they run
    max(--reps, --filter-reps) times (--filter-reps 0: --reps times)."""
    seeds: str = ""
    """The seeds every condition runs, as A..B (inclusive), a comma list, or both (3..12):
    a design of new seeds, over --reps and --filter-reps. Empty: repetition r runs with seed
    r for r < --reps (--filter-reps for `learned` and the gates)."""
    select_from: str = ""
    """A finished study's directory (its runs.csv, e.g. docs/results): run only the starts
    the paper's rule selects from its runs (the learned baseline's largest failures), declared
    in OUT/selection.json before any run, and report them in OUT/heldout.md. With --seeds it
    never ran, this is the held-out test of the targeted claim (mission/study/heldout.py)."""
    steps: int = 100
    """Planning steps per run (T; each run records T + 1 coverage values)."""
    platform: tuple[str, ...] = ("flyer",)
    """Platforms: the paper's setting is the free-flying camera; `rover` is the extension.
    With more than one, or with --profiles, every (platform, profile) is a cell of its own
    (see the module docstring)."""
    profiles: tuple[str, ...] = ("nominal",)
    """Sensing profiles: nominal, degraded, drift, drift+degraded (SENSING_PROFILES; levels
    in docs/study.md). `nominal` runs the --mission.sensing settings as given; the others set
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
    resumption; see mission/study/cluster.py and docs/running.md."""
    torch_threads: int = 1
    """Torch threads per worker."""
    out: Path = Path("runs/study")
    """Directory of the study (see the module docstring); re-running resumes it."""
    bootstrap: int = 10_000
    """Paired bootstrap resamples for the confidence intervals."""
    tables_only: bool = False
    """Run nothing: rewrite OUT's tables, plots and summary.json from its runs.csv and
    coverage_curves.csv (a committed study keeps those, not its run directories), e.g. after
    a release changed the tables. The settings must match OUT/study.json as for a resume."""
    progress: bool = True
    """Show a progress bar with an ETA."""
    record: bool = False
    """Record every run's messages into OUT/runs/<id>/bag (`rovergate replay` plays one).
    Off by default: a bag holds about 165 MB per 100 steps (docs/running.md, "The flight
    recorder and replay"), which over a study's hundreds of runs is tens of GB."""
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
    "seed": "repetition r runs with seed r; use --reps N for more seeds, or --seeds A..B",
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
    # Issue 28's validation, in two studies that fit its 4 hours of compute with the held-out
    # test and the gate sweep (docs/validation.md says what they leave out). The flyer: every
    # profile, start a, seeds of its own (3 and 4: the default study ran 0-2), the new gate and
    # truth; 240 runs, about half an hour.
    "validation-flyer": {"scenes": SUITE, "starts": ("a",),
                         "conditions": ("learned", "gated", "gated-ray-inf", "gated-pose",
                                        "truth"),
                         "platform": ("flyer",), "profiles": tuple(SENSING_PROFILES),
                         "seeds": "3..4", "steps": 100},
    # The rover: every start, five seeds, truth as each cell's ceiling; the two extreme
    # profiles and the suite's first three scenes; 600 runs, about two and a half hours.
    "validation-rover": {"scenes": SUITE[:3], "starts": START_NAMES,
                         "conditions": ("learned", "gated", "gated-ray-inf", "truth"),
                         "platform": ("rover",), "profiles": ("nominal", "drift+degraded"),
                         "seeds": "0..4", "steps": 100},
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
                              f"it with mission.study.runner.preset_config({cfg.preset!r}, ...)")
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
    if cfg.seeds:
        parse_seeds(cfg.seeds)
    if cfg.select_from and not cfg.seeds:
        raise ConfigError("--select-from needs --seeds the source study never ran (e.g. "
                          "--seeds 3..12): measured on the runs it selected from, the "
                          "selection's effect is inflated by regression to the mean")
    workers = cfg.workers or os.cpu_count() or 1
    return replace(cfg, conditions=conditions, workers=workers)


def parse_seeds(text: str) -> tuple[int, ...]:
    """``"3..12"`` (inclusive), ``"3,5,7"`` or a mix (``"3..5,9"``), as sorted unique seeds."""
    seeds: set[int] = set()
    for part in text.replace(" ", "").split(","):
        m = re.fullmatch(r"(\d+)(?:\.\.(\d+))?", part)
        if not m or (m.group(2) is not None and int(m.group(2)) < int(m.group(1))):
            raise ConfigError(f"--seeds {text!r}: write A..B (inclusive, A <= B), a comma "
                              "list, or both, e.g. 3..12 or 3..7,20")
        seeds.update(range(int(m.group(1)), int(m.group(2) or m.group(1)) + 1))
    return tuple(sorted(seeds))


def run_specs(cfg: StudyConfig, only: list[tuple[str, str]] | None = None) -> list[RunSpec]:
    """Every run of the study, in a fixed order; with ``only``, of those (scene, start)
    pairs alone (a held-out test's selection: :func:`mission.study.heldout.check`)."""
    seeds = parse_seeds(cfg.seeds) if cfg.seeds else None
    specs = []
    for platform, profile in cells(cfg) or [("", "")]:
        for scene in cfg.scenes:
            for start in cfg.starts:
                if only is not None and (scene, start) not in set(only):
                    continue
                for condition in cfg.conditions:
                    reps = cfg.reps
                    if condition == "learned" or get_condition(condition).withholds:
                        reps = max(reps, cfg.filter_reps)
                    specs.extend(RunSpec(scene, start, condition, r, platform, profile)
                                 for r in (seeds if seeds is not None else range(reps)))
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


