"""The study: its metrics on hand-made curves, its tables on hand-made runs, a smoke study
through the command line, and resumption after the study is killed mid-way."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import ROVERGATE, wait_gone

from mission.scoring.metrics import auc, final_coverage, s70, suppression_audit
from mission.study.spec import (
    OWNED_MISSION_FLAGS,
    RunSpec,
    StudyConfig,
    StudyFlagError,
    mission_config,
    refuse_owned_mission_flags,
)
from mission.study.tables import bootstrap_ci, table1, table2
from rovergate.config import MissionConfig, SceneConfig, to_dict
from rovergate.errors import ConfigError


def test_final_coverage_auc_and_s70_on_hand_made_curves():
    curve = [0.0, 0.2, 0.4, 0.6, 0.8]
    assert final_coverage(curve) == 0.8
    assert auc(curve) == pytest.approx(0.4)  # a straight ramp: half its end value
    assert auc([0.5] * 11) == pytest.approx(0.5)
    # 70% of a baseline of 0.8 is 0.56: first reached at step 3.
    assert s70(curve, 0.8) == (3, True)
    assert s70(curve, 0.0) == (0, True)
    # Never reached within T = 4 steps: counted as T + 1 = 5, flagged.
    assert s70(curve, 2.0) == (5, False)


def test_suppression_audit_counts_withheld_points_and_true_false_positives():
    reference = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]], dtype=np.float32)
    predicted = np.array([[0.1, 0.0, 0.0],    # near the true surface, kept
                          [10.2, 0.0, 0.0],   # near it, withheld: not a false positive
                          [5.0, 5.0, 5.0],    # far from it, withheld: a false positive
                          [6.0, 5.0, 5.0]],   # far, kept
                         dtype=np.float32)
    kept = predicted[[0, 3]]
    # Withheld 2, of which 1 false positive, of the prediction's 2 false positives.
    assert suppression_audit(predicted, kept, reference, delta_m=0.5) == (2, 1, 2)
    assert suppression_audit(predicted, predicted, reference, delta_m=0.5) == (0, 0, 2)
    assert suppression_audit(predicted[:0], kept, reference, delta_m=0.5) == (0, 0, 0)


def test_bootstrap_interval_brackets_the_mean_and_is_seeded():
    x = np.array([0.1, 0.3, -0.2, 0.4, 0.0])
    lo, hi = bootstrap_ci(x, 2000)
    assert lo < x.mean() < hi and (lo, hi) == bootstrap_ci(x, 2000)
    assert bootstrap_ci(np.array([0.2]), 100) == (0.2, 0.2)


def _row(scene, start, condition, rep, c_t, auc_, s70_, reached=True, held=None, share=None):
    return {"scene": scene, "start": start, "condition": condition, "rep": rep,
            "final_coverage": c_t, "auc": auc_, "s70": s70_, "s70_reached": reached,
            "suppressed_per_step": held, "suppressed_fp_share": share}


def test_table1_pairs_runs_and_splits_low_and_high_starts():
    rows = [
        _row("s", "a", "learned", 0, 0.60, 0.40, 40),   # low start
        _row("s", "a", "obs", 0, 0.70, 0.45, 30),
        _row("s", "b", "learned", 0, 0.90, 0.70, 20),   # high start
        _row("s", "b", "obs", 0, 0.80, 0.60, 31, reached=False),
        _row("s", "c", "learned", 0, 0.80, 0.60, 25),   # neither
        _row("s", "c", "obs", 0, 0.80, 0.60, 25),
    ]
    text, fig = table1(rows, ("obs", "learned"), 1000, steps=30)
    assert fig["learned"]["All"]["final_coverage"]["mean"] == pytest.approx(np.mean([.6, .9, .8]))
    assert fig["obs"]["Low"]["final_coverage"]["mean"] == pytest.approx(0.10)
    assert fig["obs"]["High"]["final_coverage"]["mean"] == pytest.approx(-0.10)
    assert fig["obs"]["High"]["s70"]["mean"] == pytest.approx(11.0)
    assert fig["obs"]["All"]["final_coverage"]["n"] == 3
    assert fig["obs"]["All"]["s70_unreached"] == 1
    assert "| Obs. only | All (n=3) | +0.000" in text and "Low (n=1)" in text


def test_table2_gives_mean_and_std_over_repetitions_per_start():
    rows = []
    for rep, (lc, gc) in enumerate([(0.5, 0.6), (0.7, 0.7), (0.6, 0.8)]):
        rows += [_row("s", "a", "learned", rep, lc, 0, 0),
                 _row("s", "a", "gated", rep, gc, 0, 0, held=10.0, share=0.5)]
    text, fig = table2(rows, 1000)
    # Deltas +0.1, 0, +0.2: half of the 8 sign assignments reach |mean| 0.1, so p = 0.5;
    # one start, so Holm leaves it; no curves, so no bit-identical count.
    assert "| s/a | 0.600 ± 0.100 | 0.700 ± 0.100 | +0.100 | 3 | 0.50 | 0.50 | — | 10 | 0.50 |" \
        in text
    assert fig["starts"]["s/a"]["delta"]["mean"] == pytest.approx(0.1)
    assert fig["starts"]["s/a"]["delta"]["n"] == 3
    assert fig["starts"]["s/a"]["p_signflip"] == pytest.approx(0.5)


#: A small study: 10 runs of 3 steps.
STUDY = ("study", "--scenes", "arch_field", "--starts", "a", "b", "--conditions", "obs",
         "learned", "gated", "--reps", "1", "--filter-reps", "2", "--steps", "3",
         "--bootstrap", "200")


def study(out: Path, *extra: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([*ROVERGATE, *STUDY, "--no-progress", "--out", str(out), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


#: runs.csv's columns that measure what a run cost, which differ from one run to the next.
COSTS = ("peak_rss_mb", "energy_compute_kj")


def results(out: Path) -> list[dict]:
    """runs.csv without the columns that time the run or measure its costs."""
    with open(out / "runs.csv") as f:
        return [{k: v for k, v in r.items() if not k.endswith("_s") and k not in COSTS}
                for r in csv.DictReader(f)]


@pytest.mark.e2e
def test_smoke_study_writes_every_output_and_is_the_same_in_any_worker(tmp_path: Path):
    one = study(tmp_path / "one", "--workers", "1")
    two = study(tmp_path / "two", "--workers", "2")
    for p in (one, two):
        _, err = p.communicate(timeout=400)
        assert p.returncode == 0, err[-3000:]
    out = tmp_path / "two"
    for name in ("runs.csv", "table1.md", "table2.md", "summary.json", "study.json",
                 "coverage_curves.csv",
                 "coverage_obs.png", "coverage_learned.png", "coverage_gated.png"):
        assert (out / name).stat().st_size > 0, name
    rows = results(out)
    # 2 starts x (obs once, learned and gated twice each).
    assert len(rows) == 10
    assert {(r["condition"], r["rep"]) for r in rows} == {
        ("obs", "0"), ("learned", "0"), ("learned", "1"), ("gated", "0"), ("gated", "1")}
    assert all(0 < float(r["final_coverage"]) <= 1 for r in rows)
    table = (out / "table1.md").read_text()
    assert "Learned (abs.)" in table and "Obs. only" in table and "[" in table
    assert "arch_field/a" in (out / "table2.md").read_text()
    # Costs measured in the run itself: its CPU seconds, its process's peak, the energy model.
    m = json.loads((out / "runs" / "arch_field-a-learned-r0" / "metrics.json").read_text())
    assert m["cpu_s"] > 0 and 100 < m["peak_rss_mb"] < 20_000 and m["peak_rss_scope"] == "run"
    assert m["energy_j"]["compute_j"] == pytest.approx(m["cpu_s"] * 280 / 64)
    assert "## What the runs cost" in table
    # Same seeds, same runs, whichever worker ran them and in whichever order.
    assert results(tmp_path / "one") == rows


@pytest.mark.e2e
def test_a_killed_study_resumes_and_loses_only_runs_in_flight(tmp_path: Path, launch):
    out = tmp_path / "study"
    runs = out / "runs"
    p = launch(*STUDY, "--out", str(out), "--workers", "1", new_session=True)
    p.wait_for_lines(r"run \S+ finished in", 3, timeout_s=300)
    os.killpg(p.proc.pid, signal.SIGKILL)  # the study and its workers, as a kill -9 of the job
    p.finish(60)
    before = {d.name: (d / "metrics.json").stat().st_mtime_ns for d in runs.iterdir()
              if (d / "metrics.json").exists()}
    assert 3 <= len(before) < 10
    resumed = study(out, "--workers", "2")
    _, err = resumed.communicate(timeout=400)
    assert resumed.returncode == 0, err[-3000:]
    assert f"{len(before)} finished before, {10 - len(before)} to run" in err
    assert not list(runs.glob(".*"))  # the in-flight leftovers are gone
    assert len(results(out)) == 10
    # The finished runs were kept, not redone.
    assert {n: (runs / n / "metrics.json").stat().st_mtime_ns for n in before} == before
    reference = study(tmp_path / "whole", "--workers", "2")
    _, err = reference.communicate(timeout=400)
    assert reference.returncode == 0, err[-3000:]
    assert results(out) == results(tmp_path / "whole")


@pytest.mark.e2e
def test_study_refuses_bad_settings_in_one_line(tmp_path: Path):
    r = subprocess.run([*ROVERGATE, "study", "--starts", "z", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "has no start 'z'" in r.stderr
    r = subprocess.run([*ROVERGATE, "study", "--conditions", "psychic", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "unknown condition 'psychic'" in r.stderr


@pytest.mark.e2e
def test_a_terminated_study_stops_its_workers(tmp_path: Path, launch):
    """SIGTERM (or Ctrl-C) on the study stops its worker processes too, not only itself."""
    p = launch(*STUDY, "--out", str(tmp_path / "s"), "--workers", "2")
    # The first run finished: the workers are up. They are the study's child processes (a
    # worker between two runs holds none in flight, so the runs' directories would miss it).
    p.wait_for_lines(r"run \S+ finished in", 1, timeout_s=120)
    children = Path(f"/proc/{p.proc.pid}/task/{p.proc.pid}/children")
    workers = {int(pid) for pid in children.read_text().split()}
    assert workers, "the study has no worker process"
    p.proc.send_signal(signal.SIGTERM)
    assert p.finish(60) == 130 and "re-run the same command to resume" in p.text
    for pid in workers:
        assert wait_gone(pid, 30), f"worker {pid} still running 30 s after the study stopped"


@pytest.mark.parametrize("argv, message", [
    (["--mission.platform", "rover"], "--mission.platform is set by the study for every run; "
                                      "use --platform rover"),
    (["--steps", "5", "--mission.steps=50"], "--mission.steps is set by the study for every "
                                             "run; use --steps 50"),
    (["--mission.scene.name", "crater"], "--mission.scene.name is set by the study for every "
                                         "run; use --scenes crater"),
    (["--mission.no-progress"], "--mission.no-progress is set by the study for every run; "
                                "use --progress or --no-progress (the study's progress bar)"),
    (["--mission.in_process"], "--mission.in_process is set by the study for every run; "
                               "every run is in process; leave it out"),
    (["--mission.seed", "3"], "--mission.seed is set by the study for every run; repetition r "
                              "runs with seed r; use --reps N for more seeds, or --seeds A..B"),
    (["--mission.out"], "--mission.out is set by the study for every run; use --out VALUE "
                        "(each run goes to OUT/runs/<id>)"),
])
def test_study_refuses_mission_flags_it_sets_itself(argv, message):
    with pytest.raises(StudyFlagError) as e:
        refuse_owned_mission_flags(argv)
    assert str(e.value) == message


@pytest.mark.parametrize("flag", ["--mission.contact.period-steps", "--mission.planner.command",
                                  "--mission.planner.programs", "--mission.max-restarts",
                                  "--mission.listen",
                                  "--mission.step-timeout-s=5"])
def test_study_refuses_mission_flags_that_only_the_process_set_reads(flag):
    with pytest.raises(StudyFlagError, match="has no effect on a study: every run is in one "
                                             "process"):
        refuse_owned_mission_flags([flag, "3"])


def test_study_checks_every_mission_setting_before_any_run(tmp_path: Path):
    from mission.study.spec import check_study
    from rovergate.errors import ConfigError, UnknownNameError
    base = StudyConfig(scenes=("arch_field",), starts=("a",), conditions=("obs",), steps=2,
                       out=tmp_path)
    with pytest.raises(UnknownNameError, match="unknown platform 'boat'"):
        check_study(replace(base, platform="boat"))
    bad_gate = replace(base.mission, gate=replace(base.mission.gate, k=0))
    with pytest.raises(ConfigError, match="--gate.k must be at least 1"):
        check_study(replace(base, mission=bad_gate))


def test_study_lets_every_other_mission_flag_through():
    refuse_owned_mission_flags(["--platform", "rover", "--steps", "5", "--out", "runs/x",
                                "--mission.sensing.noise-frac", "0.01", "--mission.gate.k=3",
                                "--mission.scene.up-axis", "y", "--mission.planner.name",
                                "beam", "--no-progress"])


def test_the_refused_flags_are_exactly_what_the_study_sets():
    """Set every field to a value the study does not use: what it changed is what it owns."""
    own = MissionConfig(scene=SceneConfig(name="mine.ply", d_scene_m=7.0,
                                          bounds_m=(1, 2, 3, 4, 5, 6)),
                        platform="other", start="q", steps=999, seed=99, condition="truth",
                        out=Path("elsewhere"), in_process=False, progress=True, record=True,
                        viz=True, ros2=True)
    made = mission_config(StudyConfig(mission=own), RunSpec("crater", "b", "obs", 0),
                          Path("runs/x"))

    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            key = prefix + k.replace("_", "-")
            out.update(flat(v, key + ".") if isinstance(v, dict) else {key: v})
        return out
    before, after = flat(to_dict(own)), flat(to_dict(made))
    changed = {k for k in before if before[k] != after[k]}
    assert changed == set(OWNED_MISSION_FLAGS) - {"scene"}  # `scene` is --scenes' alias


@pytest.mark.e2e
def test_a_mission_flag_of_the_study_refused_before_anything_starts(tmp_path: Path):
    r = subprocess.run([*ROVERGATE, "study", "--mission.platform", "rover", "--mission.steps",
                        "50", "--out", str(tmp_path / "s")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and r.stderr == ("error: --mission.platform is set by the study "
                                              "for every run; use --platform rover\n")
    assert not (tmp_path / "s").exists()


@pytest.mark.e2e
def test_other_mission_flags_reach_every_run(tmp_path: Path):
    out = tmp_path / "s"
    r = subprocess.run([*ROVERGATE, "study", "--scenes", "arch_field", "--starts", "a",
                        "--conditions", "learned", "--reps", "1", "--filter-reps", "1",
                        "--steps", "2", "--workers", "1", "--bootstrap", "200",
                        "--no-progress", "--out", str(out),
                        "--mission.sensing.noise-frac", "0.01", "--mission.gate.k", "3",
                        "--record", "--mission.record-compression", "zstd"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    (run,) = (out / "runs").iterdir()
    saved = json.loads((run / "config.json").read_text())
    assert saved["sensing"]["noise_frac"] == 0.01 and saved["gate"]["k"] == 3
    assert (saved["steps"], saved["platform"], saved["in_process"]) == (2, "flyer", True)
    # --record: the run's bag is in its directory, where `rovergate replay` takes it.
    recording = json.loads((run / "metrics.json").read_text())["recording"]
    assert recording["path"] == str(run / "bag") and recording["compression"] == "zstd"
    assert (run / "bag" / "metadata.yaml").is_file()


# ----------------------------------------------------------------------------- cells

def test_the_validation_preset_stands_for_its_flags_and_a_flag_given_wins(tmp_path: Path):
    import tyro

    from mission.study.spec import (
        SENSING_PROFILES,
        VALIDATION_CONDITIONS,
        cells,
        check_study,
        preset_args,
        preset_config,
        run_specs,
    )

    def parsed(*argv):
        return check_study(tyro.cli(StudyConfig, args=preset_args([*argv, "--out",
                                                                   str(tmp_path)])))
    cfg = parsed("--preset", "validation")
    assert cfg.platform == ("flyer", "rover") and cfg.profiles == tuple(SENSING_PROFILES)
    assert set(cfg.conditions) == set(VALIDATION_CONDITIONS) and cfg.steps == 100
    assert len(cells(cfg)) == 8
    specs = run_specs(cfg)
    # 6 scenes x start a x 5 conditions x 4 profiles x 2 platforms x 2 repetitions.
    assert len(specs) == 480 == len({s.id for s in specs})
    assert "rover-drift+degraded-crater-a-gated-pose-r1" in {s.id for s in specs}
    assert run_specs(check_study(replace(preset_config("validation"), out=tmp_path))) == specs
    # A flag given wins over the preset's, even one equal to the default.
    mine = parsed("--preset=validation", "--reps", "3", "--filter-reps", "3", "--platform",
                  "rover")
    assert mine.platform == ("rover",) and len(run_specs(mine)) == 6 * 5 * 4 * 3
    with pytest.raises(ConfigError, match="'fast' is not a preset; the presets are validation"):
        preset_args(["--preset", "fast"])


def test_a_profile_sets_its_sensing_fields_over_the_missions_and_nothing_else():
    from mission.study.spec import DEGRADED, DRIFT, SENSING_PROFILES
    own = MissionConfig()
    own.sensing = replace(own.sensing, noise_frac=0.05, dropout_pixel_prob=0.2)
    study_cfg = StudyConfig(mission=own, platform=("flyer", "rover"))
    nominal = mission_config(study_cfg, RunSpec("crater", "a", "gated", 1, "rover", "nominal"),
                             Path("x"))
    assert nominal.platform == "rover" and nominal.sensing == own.sensing
    both = mission_config(study_cfg, RunSpec("crater", "a", "gated", 1, "flyer",
                                             "drift+degraded"), Path("x"))
    assert both.platform == "flyer"
    for k, v in {**DRIFT, **DEGRADED}.items():
        assert getattr(both.sensing, k) == v
    assert both.sensing.dropout_pixel_prob == 0.2  # not the profile's: the mission's
    assert both.sensing.noise_frac == SENSING_PROFILES["degraded"]["noise_frac"]
    assert both.sensing.drifts and not nominal.sensing.drifts


def test_a_study_of_one_platform_keeps_its_settings_and_run_ids(tmp_path: Path):
    """A plain study saves study.json as before cells existed, so it still resumes."""
    from mission.study.runner import _settings
    from mission.study.spec import check_study, run_specs
    cfg = check_study(StudyConfig(scenes=("arch_field",), starts=("a",), conditions=("obs",),
                                  reps=1, filter_reps=1, out=tmp_path))
    assert _settings(cfg)["platform"] == "flyer" and "profiles" not in _settings(cfg)
    assert {s.id for s in run_specs(cfg)} == {"arch_field-a-obs-r0", "arch_field-a-learned-r0"}


def test_study_refuses_an_unknown_profile_in_one_line(tmp_path: Path):
    from mission.study.spec import check_study
    with pytest.raises(ConfigError, match="--profiles: 'foggy' is not a sensing profile; the "
                                          "profiles are nominal, degraded, drift"):
        check_study(StudyConfig(profiles=("foggy",), out=tmp_path))


def test_validation_tables_pool_suppression_as_ratios_of_sums():
    from mission.study.validation import suppression
    rows = [{"steps": 10, "suppressed_per_step": 10.0, "suppressed_fp_share": 0.9,
             "predicted_fp_per_step": 20.0, "wrongly_withheld_per_step": 1.0},
            {"steps": 10, "suppressed_per_step": 1.0, "suppressed_fp_share": 0.0,
             "predicted_fp_per_step": 5.0, "wrongly_withheld_per_step": 1.0}]
    # A run that withheld nothing has no share, and still had false positives to withhold.
    rows.append({"steps": 10, "suppressed_per_step": 0.0, "suppressed_fp_share": None,
                 "predicted_fp_per_step": 10.0, "wrongly_withheld_per_step": 1.0})
    s = suppression(rows)
    # 90 of 110 withheld points were false positives (a mean of shares would say 0.45).
    assert s["precision"] == pytest.approx(90 / 110)
    assert s["recall"] == pytest.approx(90 / 350)
    assert s["wrongly_withheld_per_step"] == 1.0
    # The tables print each share with the point-steps it is of.
    from mission.study.validation import _share
    assert s["recalled"] == pytest.approx(90)
    assert _share(s["precision"], s["withheld_fp"], s["withheld"]) == "0.82 (90 / 110)"
    assert _share(s["recall"], 2e6 * s["recall"], 2e6) == "0.26 (514k / 2.0M)"
    assert _share(None, 0.0, 0.0) == "—"


@pytest.mark.e2e
def test_a_study_of_cells_writes_each_cell_and_the_validation_tables(tmp_path: Path):
    out = tmp_path / "v"
    r = subprocess.run([*ROVERGATE, "study", "--platform", "flyer", "rover", "--profiles",
                        "nominal", "drift", "--scenes", "arch_field", "--starts", "a",
                        "--conditions", "gated-pose", "--reps", "1", "--filter-reps", "1",
                        "--steps", "2", "--workers", "2", "--bootstrap", "200",
                        "--no-progress", "--out", str(out)],
                       capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = results(out)
    assert len(rows) == 2 * 2 * 2  # platforms x profiles x (learned, gated-pose)
    assert {(x["platform"], x["profile"]) for x in rows} == {
        (p, s) for p in ("flyer", "rover") for s in ("nominal", "drift")}
    for cell in ("flyer-nominal", "flyer-drift", "rover-nominal", "rover-drift"):
        assert "Learned (abs.)" in (out / cell / "table1.md").read_text()
        assert len(results(out / cell)) == 2
    drifted = json.loads((out / "runs" / "rover-drift-arch_field-a-gated-pose-r0" /
                          "config.json").read_text())
    assert drifted["platform"] == "rover" and drifted["sensing"]["drift_xy_m"] > 0
    text = (out / "validation.md").read_text()
    assert "## rover, drift" in text and "Gate, pose-aware" in text and "Placebo" in text
    # Each gate's pooled suppression per platform, with its point-steps.
    assert re.search(r"- rover, Gate, pose-aware: suppression precision (—|[0-9.]+ \()", text)
    for name in ("validation_coverage.png", "validation_suppression.png", "summary.json"):
        assert (out / name).stat().st_size > 0


def test_a_preset_named_in_python_without_its_settings_is_refused(tmp_path: Path):
    from mission.study.spec import check_study
    with pytest.raises(ConfigError, match="alone sets nothing; build it with "
                                          "mission.study.runner.preset_config"):
        check_study(StudyConfig(preset="validation", out=tmp_path))


def test_a_study_saved_before_a_mission_setting_existed_still_resumes(tmp_path: Path):
    """Settings saved without a mission setting added since are read with it at its
    default (what those runs ran with), so the study resumes."""
    from mission.study.runner import _normalised, _settings
    from mission.study.spec import check_study
    cfg = check_study(StudyConfig(scenes=("arch_field",), starts=("a",), conditions=("obs",),
                                  reps=1, filter_reps=1, out=tmp_path))
    now = _settings(cfg)
    old = json.loads(json.dumps(now))
    del old["mission"]["planner"]["beam_discount"]
    assert old != now and _normalised(old) == now
    other = json.loads(json.dumps(now))
    other["mission"]["gate"]["k"] = 5
    assert _normalised(other) != now


def test_issue_28s_validation_presets_run_their_own_seeds_and_truth(tmp_path: Path):
    import tyro

    from mission.study.spec import check_study, preset_args, run_specs

    def specs(name):
        cfg = check_study(tyro.cli(StudyConfig, args=preset_args(
            ["--preset", name, "--out", str(tmp_path)])))
        return run_specs(cfg)
    flyer, rover = specs("validation-flyer"), specs("validation-rover")
    assert len(flyer) == 6 * 1 * 5 * 4 * 2 and len(rover) == 3 * 5 * 4 * 2 * 5
    # The flyer's nominal cell has seeds of its own: the default study ran 0, 1 and 2.
    assert {s.rep for s in flyer} == {3, 4}
    assert {s.rep for s in rover} == set(range(5)) and {s.start for s in rover} == set("abcde")
    for runs in (flyer, rover):
        assert {"truth", "gated-ray-inf", "learned", "gated"} <= {s.condition for s in runs}
