"""The held-out test of the targeted claim (mission/study/heldout.py) and the cross-fit strata
(mission/study/tables.py): the seeds it takes, the selection it declares before any run, the
refusals, and on hand-made runs that a selected effect vanishes where the choice is held out."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mission.study import heldout
from mission.study.spec import StudyConfig, parse_seeds, run_specs
from mission.study.tables import crossfit, crossfit_strata
from rovergate.errors import ConfigError


def run(scene, start, condition, rep, c_t) -> dict:
    return {"scene": scene, "start": start, "condition": condition, "rep": rep, "seed": rep,
            "final_coverage": c_t, "auc": 0.5, "s70": 10, "s70_reached": True,
            "suppressed_per_step": None, "suppressed_fp_share": None}


def write_source(path: Path, rows: list[dict]) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    with open(path / "runs.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["scene", "start", "condition", "rep", "seed",
                                          "final_coverage"], extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return path


def source_rows(gap=lambda i: 0.1 * (i % 2)) -> list[dict]:
    """Eight starts of scene arch_field and crater (a..d), seeds 0-2: start i's learned C_T
    falls with i, truth sits ``gap(i)`` above learned, gated equals learned."""
    rows = []
    for i, (scene, start) in enumerate((s, x) for s in ("arch_field", "crater")
                                       for x in "abcd"):
        for r in range(3):
            learned = 0.95 - 0.05 * i
            rows += [run(scene, start, "learned", r, learned),
                     run(scene, start, "gated", r, learned),
                     run(scene, start, "truth", r, learned + gap(i))]
    return rows


@pytest.mark.parametrize("text, seeds", [("3..12", tuple(range(3, 13))), ("5", (5,)),
                                         ("3..5,9,4", (3, 4, 5, 9)), (" 7 , 7 ", (7,))])
def test_seeds_are_ranges_and_lists(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize("text", ["", "3..", "12..3", "a", "3-5", "-1"])
def test_a_bad_seed_list_is_one_line_that_shows_the_form(text):
    with pytest.raises(ConfigError, match="write A..B"):
        parse_seeds(text)


def test_the_selection_is_declared_once_and_a_changed_source_is_refused(tmp_path: Path):
    src = write_source(tmp_path / "src", source_rows())
    out = tmp_path / "out"
    out.mkdir()
    decl = heldout.declare(src, out, (3, 4))
    saved = json.loads((out / "selection.json").read_text())
    assert saved["declared"] and saved["seeds"] == [3, 4] and saved["source_seeds"] == [0, 1, 2]
    # The six lowest learned starts: crater d, c, b, a, then arch_field d, c.
    assert decl["lowest_learned"] == ["crater/d", "crater/c", "crater/b", "crater/a",
                                      "arch_field/d", "arch_field/c"]
    assert decl["largest_truth_gap"][:4] == ["arch_field/b", "arch_field/d", "crater/b",
                                             "crater/d"]
    assert set(decl["starts"]) == set(decl["lowest_learned"]) | set(decl["largest_truth_gap"])
    assert heldout.declare(src, out, (3, 4)) == decl  # a resume finds the same declaration
    with pytest.raises(ConfigError, match="declares another selection"):
        heldout.declare(src, out, (3, 4, 5))
    rows = source_rows()
    rows[0]["final_coverage"] = 0.1  # arch_field/a becomes a failure: the selection moves
    write_source(src, rows)
    with pytest.raises(ConfigError, match="declares another selection"):
        heldout.declare(src, out, (3, 4))


def test_a_held_out_study_refuses_seeds_the_source_ran_and_runs_only_the_selection(
        tmp_path: Path):
    # The truth gap grows as learned falls: both selections are the six lowest starts.
    src = write_source(tmp_path / "src", source_rows(gap=lambda i: 0.01 * i))
    cfg = StudyConfig(scenes=("arch_field", "crater"), conditions=("learned", "gated"),
                      select_from=str(src), seeds="2..4", out=tmp_path / "out")
    with pytest.raises(ConfigError, match="2 were run by the study at --select-from"):
        heldout.check(cfg)
    cfg.seeds = "3..4"
    only = heldout.check(cfg)
    specs = run_specs(cfg, only)
    assert {(s.scene, s.start) for s in specs} == set(only) and len(only) == 6
    assert {s.rep for s in specs} == {3, 4} and {s.condition for s in specs} == {"learned",
                                                                                "gated"}
    with pytest.raises(ConfigError, match="no runs.csv there"):
        heldout.source_rows(tmp_path)


def test_the_report_pairs_new_seeds_and_sets_them_beside_the_selected_figure(tmp_path: Path):
    rows = source_rows()
    for r in rows:  # in the source, gated gained 0.2 at the failures it was selected on
        if r["condition"] == "gated" and r["start"] in "cd":
            r["final_coverage"] += 0.2
    src = write_source(tmp_path / "src", rows)
    decl = {**heldout.choose(src), "seeds": list(range(3, 13))}
    new = []
    for name in decl["starts"]:
        scene, start = name.split("/")
        for seed in range(3, 13):
            learned = 0.6 + 0.01 * (seed % 2)
            new += [run(scene, start, "learned", seed, learned),
                    run(scene, start, "gated", seed, learned + 0.05)]
    text, fig = heldout.heldout_table(new, decl, ("learned", "gated"), 500)
    gated = fig["conditions"]["gated"]
    for s in gated["starts"].values():
        assert s["delta"] == pytest.approx(0.05)
        assert s["p_signflip"] == pytest.approx(2 ** -9)  # 10 same-sign changes
        assert s["p_holm"] == pytest.approx(len(decl["starts"]) * 2 ** -9)
    both = gated["groups"]["Both selections"]
    assert both["mean"] == pytest.approx(0.05) and both["n"] == len(decl["starts"])
    # Placebo: odd seeds (0.61) against even seeds (0.60) in seed order 3..12.
    assert both["placebo"]["mean"] == pytest.approx(-0.01)
    a = gated["groups"]["Selection (a): lowest learned C_T"]
    assert a["in_sample"]["mean"] == pytest.approx(0.2 * 4 / 6)  # c and d of both scenes
    assert "p (Holm)" in text and " *" in text


def test_crossfit_strata_show_a_gain_that_was_selected():
    """A start with one bad learned run falls in Low only when that run is used to choose it;
    the gated run is flat, so its in-sample gain is all regression to the mean."""
    rows = []
    for start, learned in (("a", [0.3, 0.9, 0.9]), ("b", [0.9, 0.9, 0.9]),
                           ("c", [0.95, 0.95, 0.95])):
        for r, v in enumerate(learned):
            rows += [run("s", start, "learned", r, v), run("s", start, "gated", r, 0.9)]
    fig = crossfit_strata(rows, "gated", 200)
    assert fig["Low"]["in_sample"]["mean"] == pytest.approx(0.2)  # (0.6 + 0 + 0) / 3
    assert fig["Low"]["mean"] == pytest.approx(0.0)  # folds 1, 2 choose it; their change: 0
    assert fig["Low"]["n"] == 1
    assert fig["High"]["in_sample"]["mean"] == pytest.approx(np.mean([0.0, -0.05]))
    text, figures = crossfit(rows, ("learned", "gated"), 200)
    assert "chosen on the other repetitions" in text and set(figures) == {"gated"}
    one = [r for r in rows if r["rep"] == 0]
    assert crossfit(one, ("learned", "gated"), 200)[1] == {}


def test_a_selection_without_new_seeds_is_refused_before_anything_runs(tmp_path: Path):
    from mission.study.spec import check_study
    src = write_source(tmp_path / "src", source_rows())
    with pytest.raises(ConfigError, match="--select-from needs --seeds"):
        check_study(StudyConfig(scenes=("arch_field",), starts=("a",),
                                conditions=("learned",), select_from=str(src),
                                out=tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_the_energy_model_and_the_cost_table():
    from mission.scoring.energy import CORE_W, energy
    from mission.study.tables import costs
    rover = energy("rover", 37.0, 10.0)
    assert rover["drive_j"] == pytest.approx(100_000.0)  # 100 W for 37 m at 3.7 cm/s
    assert rover["compute_j"] == pytest.approx(10.0 * CORE_W) and CORE_W == 4.375
    assert rover["total_j"] == pytest.approx(rover["drive_j"] + rover["compute_j"])
    flyer = energy("flyer", 37.0, 10.0)
    assert flyer["drive_j"] is None and flyer["total_j"] is None  # no published figure
    rows = [{"condition": "learned", "median_step_s": s, "gate_s": 0.01, "plan_s": 0.05,
             "cpu_s": 20.0 + i, "peak_rss_mb": 900.0 + 100 * i, "energy_drive_kj": 50.0,
             "energy_compute_kj": 0.1} for i, s in enumerate((0.1, 0.2, 0.3))]
    rows.append({"condition": "obs", "median_step_s": 0.1})  # a run from before the costs
    text, fig = costs(rows, ("obs", "learned"))
    assert fig["learned"]["step_ms"] == pytest.approx(200.0)
    assert fig["learned"]["peak_rss_mb"] == 1000.0 and fig["learned"]["peak_rss_mb_max"] == 1100
    assert fig["learned"]["cpu_s"] == 21.0 and fig["learned"]["drive_kj"] == 50.0
    assert fig["obs"]["cpu_s"] is None and "| Obs. only | 1 | 100 | — |" in text


def test_the_sweep_chooses_the_largest_recall_at_the_precision_or_says_it_missed():
    from mission.study.sweep import choose
    figs = {"k1-eps0.03": {"precision": 0.95, "recall": 0.2},
            "k1-eps0.06": {"precision": 0.91, "recall": 0.4},
            "k2-eps0.03": {"precision": 0.5, "recall": 0.9},
            "k3-eps0.03": {"precision": None, "recall": 0.0}}  # withheld nothing
    assert choose(figs, 0.9) == ("k1-eps0.06", True)
    assert choose(figs, 0.99) == ("k1-eps0.03", False)  # none reaches it: the most precise
