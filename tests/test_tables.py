"""The study's statistics on hand-made runs (no missions): pairing over repetitions, strata
from the mean, the placebo, the sign-flip test, Holm and Benjamini–Hochberg, the sign test,
bit-identical runs, the paper's selection, the failure modes and what write_tables writes."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mission.study.spec import StudyConfig, run_specs
from mission.study.tables import (
    PLACEBO_LABEL,
    bh,
    bootstrap_ci,
    failure_modes,
    holm,
    identical_runs,
    paper_selection,
    per_start_effects,
    placebo_effects,
    robustness,
    rows_from_csv,
    sign_test,
    signflip_p,
    strata,
    table1,
    table2,
    write_tables,
)
from rovergate.errors import ConfigError


def run(start, condition, rep, c_t, auc=0.5, s70=10, scene="s", **extra) -> dict:
    return {"scene": scene, "start": start, "condition": condition, "rep": rep,
            "final_coverage": c_t, "auc": auc, "s70": s70, "s70_reached": True,
            "suppressed_per_step": None, "suppressed_fp_share": None, **extra}


def runs_of(start, condition, values, **extra) -> list[dict]:
    """One run per repetition 0, 1, ... with these final coverages."""
    return [run(start, condition, r, v, **extra) for r, v in enumerate(values)]


# ----------------------------------------------------------------------------- placebo

def test_placebo_is_odd_half_minus_even_half_of_the_learned_runs():
    rows = (runs_of("a", "learned", [0.5, 0.8, 0.6])              # r1 − mean(r0, r2)
            + runs_of("b", "learned", [0.1, 0.2, 0.3, 0.5])       # mean(r1, r3) − mean(r0, r2)
            + runs_of("c", "learned", [0.9])                      # one run: undefined
            + [run("d", "learned", 1, 0.4), run("d", "learned", 2, 0.7)]  # r0 missing
            + runs_of("a", "gated", [0.0, 0.0, 0.0]))             # other conditions ignored
    p = placebo_effects(rows, "final_coverage")
    assert p[("s", "a")] == pytest.approx(0.8 - 0.55)
    assert p[("s", "b")] == pytest.approx(0.35 - 0.2)
    assert p[("s", "c")] is None
    # By position among the runs there are: the second run against the first.
    assert p[("s", "d")] == pytest.approx(0.7 - 0.4)


def test_table1_has_a_placebo_row_pooled_over_starts():
    rows = (runs_of("a", "learned", [0.5, 0.8, 0.6], auc=0.4)
            + runs_of("b", "learned", [0.7, 0.6, 0.5], auc=0.4))
    text, fig = table1(rows, ("learned",), 500, steps=30)
    placebo = fig["placebo"]["All"]["final_coverage"]
    assert placebo["mean"] == pytest.approx(np.mean([0.8 - 0.55, 0.6 - 0.6]))
    assert placebo["n"] == 2
    assert fig["placebo"]["All"]["auc"]["mean"] == pytest.approx(0.0)
    assert f"| {PLACEBO_LABEL} | All (n=2) | +0.125 [" in text


def test_placebo_with_one_repetition_is_a_dash():
    rows = runs_of("a", "learned", [0.5]) + runs_of("a", "obs", [0.6])
    text, fig = table1(rows, ("obs", "learned"), 500, steps=30)
    assert f"| {PLACEBO_LABEL} | All (n=0) | — | — | — |" in text
    assert fig["placebo"]["All"]["final_coverage"] == {"mean": None, "ci95": None, "n": 0}
    # The paired row still has its one pair.
    assert fig["obs"]["All"]["final_coverage"]["mean"] == pytest.approx(0.1)


# ----------------------------------------------------------------------------- Table 1

def test_strata_follow_the_mean_learned_coverage_not_repetition_0():
    rows = (runs_of("lowish", "learned", [0.90, 0.60, 0.60])      # r0 High, mean 0.70: Low
            + runs_of("highish", "learned", [0.70, 0.95, 0.95])   # r0 Low, mean 0.867: High
            + runs_of("mid", "learned", [0.80, 0.80, 0.80]))
    groups = strata(rows)
    assert groups["Low"] == [("s", "lowish")]
    assert groups["High"] == [("s", "highish")]
    assert len(groups["All"]) == 3


def test_table1_pairs_every_repetition_by_seed_and_resamples_starts():
    rows = (runs_of("a", "learned", [0.5, 0.6, 0.7])
            + runs_of("a", "obs", [0.6, 0.6, 0.9])               # deltas +0.1, 0, +0.2
            + runs_of("b", "learned", [0.8, 0.8])
            + runs_of("b", "obs", [0.7, 0.9, 0.5]))              # r2 has no learned twin
    effects = per_start_effects(rows, "obs", "final_coverage")
    assert effects[("s", "a")] == pytest.approx(0.1)
    assert effects[("s", "b")] == pytest.approx(0.0)              # (−0.1 + 0.1) / 2
    text, fig = table1(rows, ("obs", "learned"), 500, steps=30)
    cell = fig["obs"]["All"]["final_coverage"]
    assert cell["mean"] == pytest.approx(0.05) and cell["n"] == 2  # n counts starts
    # The learned row: each start's mean, then the mean over starts.
    assert fig["learned"]["All"]["final_coverage"]["mean"] == pytest.approx((0.6 + 0.8) / 2)
    assert "Repetitions per start: Obs. only 2–3, Learned (abs.) 2–3" in text


# ----------------------------------------------------------------------------- tests

@pytest.mark.parametrize("deltas, p", [
    ([1, 2, 3], 0.25),                # all positive: only the two all-same-sign assignments
    ([0, 0, 0], 1.0),                 # no change: every assignment ties the observed
    ([0.1, 0.0, 0.2], 0.5),
    ([1, -1], 1.0),
    ([1, 1, 1, 1, 1, 1], 2 / 64),
    ([3, 2, 1], 0.25),                # the order of the repetitions does not matter
    ([-1, -2, -3], 0.25),             # two-sided
])
def test_signflip_p_enumerates_every_sign_assignment(deltas, p):
    assert signflip_p(deltas) == pytest.approx(p)


def test_holm_matches_the_hand_computation():
    # Sorted: 0.005*4 = 0.02, 0.01*3 = 0.03, 0.03*2 = 0.06, 0.04*1 = 0.04 -> 0.06 (monotone).
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, 0.6]) == pytest.approx([1.0, 1.0])      # capped at 1
    assert holm([0.25]) == pytest.approx([0.25])


# The study's statistics were written by hand until issue 28 moved them to scipy and
# statsmodels. The hand-written versions, kept here as the reference: the libraries must give
# the committed tables' numbers.

def _hand_bootstrap_ci(v, resamples, seed=0):
    v = np.asarray(v, dtype=np.float64)
    idx = np.random.default_rng(seed).integers(0, len(v), size=(resamples, len(v)))
    means = v[idx].mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def _hand_signflip_p(d):
    d = np.asarray(d, dtype=np.float64)
    bits = (np.arange(2 ** len(d))[:, None] >> np.arange(len(d))) & 1
    stats = np.abs(((1 - 2 * bits) * d).mean(axis=1))
    observed = abs(d.mean())
    return float(np.mean(stats >= observed - 1e-12 * max(1.0, observed)))


def _hand_holm(p):
    p = np.asarray(p, dtype=np.float64)
    order = np.argsort(p, kind="stable")
    scaled = p[order] * (len(p) - np.arange(len(p)))
    adjusted = np.empty_like(p)
    adjusted[order] = np.minimum(np.maximum.accumulate(scaled), 1.0)
    return adjusted


@pytest.mark.parametrize("seed", range(6))
def test_the_libraries_give_the_hand_written_statistics(seed):
    rng = np.random.default_rng(seed)
    for n in (2, 3, 6, 11, 30):
        v = np.round(rng.normal(0.0, 0.05, size=n), 3)  # deltas as the tables hold them
        # The same draws from the same generator: the same interval, but for the last bits
        # of a double (scipy sums the means in another order).
        assert bootstrap_ci(v, 2000, seed) == pytest.approx(_hand_bootstrap_ci(v, 2000, seed),
                                                             abs=1e-12)
        if n <= 16:
            assert signflip_p(v) == pytest.approx(_hand_signflip_p(v), abs=1e-12)
        p = rng.uniform(0, 0.2, size=n)
        p[rng.integers(n)] = p[0]  # a tie
        assert holm(p) == pytest.approx(_hand_holm(p), abs=1e-15)
    ties = np.array([0.1, -0.1, 0.1, -0.1, 0.2])  # sums equal in another order
    assert signflip_p(ties) == pytest.approx(_hand_signflip_p(ties))


def test_signflip_p_beyond_the_exact_limit_samples_and_stays_near_the_exact_value():
    d = np.random.default_rng(3).normal(0.02, 0.05, size=18)
    exact = _hand_signflip_p(d)  # 2^18 assignments, by hand
    assert signflip_p(d) == pytest.approx(exact, abs=0.01)
    assert signflip_p(d) == signflip_p(d)  # seeded


def test_benjamini_hochberg_matches_the_hand_computation():
    # Sorted p*m/i: 0.02, 0.02, 0.04, 0.04 (then the running minimum from the top).
    assert bh([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.02, 0.04, 0.04, 0.02])


def test_sign_test_counts_starts_and_drops_ties():
    t = sign_test([0.1, 0.2, -0.1, 0.0, 0.3])
    assert (t["improve"], t["worsen"], t["tie"]) == (3, 1, 1)
    assert t["expected_improve"] == 2.0
    # 3 of 4 untied: outcomes 0, 1, 3, 4 are as extreme, (1 + 4 + 4 + 1) / 16.
    assert t["p"] == pytest.approx(10 / 16)
    assert sign_test([0.0, 0.0])["p"] == 1.0


# ----------------------------------------------------------------------------- Table 2

def test_identical_runs_compare_whole_curves_of_twins():
    rows = [run("a", "learned", 0, 0.5, coverage=[0.1, 0.5]),
            run("a", "gated", 0, 0.5, coverage=[0.1, 0.5]),
            run("a", "learned", 1, 0.5, coverage=[0.2, 0.5]),
            run("a", "gated", 1, 0.5, coverage=[0.2, 0.5 + 1e-12]),  # not bit-identical
            run("a", "gated", 2, 0.5, coverage=[0.2, 0.5])]          # no learned twin
    assert identical_runs(rows) == {("s", "a"): (1, 2)}
    text, fig = table2(rows, 200)
    assert "| s/a |" in text and " | 1/2 | " in text
    assert "1 of 2 gated runs have the same coverage curve" in text
    assert fig["identical"] == {"runs": 1, "of": 2}


def test_table2_marks_starts_by_holm_adjusted_p():
    learned = [0.5] * 6
    one = runs_of("a", "learned", learned) + runs_of("a", "gated", [0.6] * 6)
    text, fig = table2(one, 200)
    # Six positive deltas: p = 2/64 < 0.05, one start: Holm leaves it, and it is marked.
    assert fig["starts"]["s/a"]["p_holm"] == pytest.approx(2 / 64)
    assert "| 6 | 0.03 | 0.03 * |" in text
    two = one + runs_of("b", "learned", learned) + runs_of("b", "gated", [0.6] * 6)
    text, fig = table2(two, 200)
    # Two such starts: Holm doubles the smaller p to 0.0625, and nothing is marked.
    assert fig["starts"]["s/a"]["p_holm"] == pytest.approx(4 / 64)
    assert fig["starts"]["s/b"]["p_bh"] == pytest.approx(2 / 64)
    assert " * |" not in text and fig["significant"]["holm"] == 0
    assert fig["significant"]["bh"] == 2


def test_table2_sign_test_and_pooled_rows_with_their_placebo():
    rows = []
    for start, (lc, gc) in {"a": ([0.5, 0.7, 0.6], [0.6, 0.8, 0.7]),    # +0.1
                            "b": ([0.9, 0.9, 0.9], [0.8, 0.8, 0.8]),    # −0.1
                            "c": ([0.8, 0.6, 0.8], [0.8, 0.6, 0.8])}.items():  # 0
        rows += runs_of(start, "learned", lc) + runs_of(start, "gated", gc)
    text, fig = table2(rows, 200)
    assert fig["sign_test"]["improve"] == 1 and fig["sign_test"]["worsen"] == 1
    assert fig["sign_test"]["tie"] == 1
    assert "1 improve, 1 worsen, 1 tie" in text
    assert fig["All starts"]["mean"] == pytest.approx(0.0) and fig["All starts"]["n"] == 3
    # Placebo per start: a 0.7 − 0.55, b 0, c 0.6 − 0.8.
    assert fig["All starts"]["placebo"]["mean"] == pytest.approx((0.15 + 0.0 - 0.2) / 3)
    # Strata by the mean learned C_T: a 0.6 Low, b 0.9 High, c 0.733 Low.
    assert fig["Low (learned C_T < 0.75)"]["starts"] == ["s/a", "s/c"]
    assert fig["High (learned C_T > 0.85)"]["starts"] == ["s/b"]


def test_paper_selection_takes_the_lowest_learned_and_the_largest_truth_gap():
    rows = []
    for i in range(8):
        learned = (i + 1) / 16                        # start 0 lowest; sums stay exact
        rows += runs_of(f"{i}", "learned", [learned, learned])
        rows += runs_of(f"{i}", "gated", [learned + i / 128, learned])
        rows += runs_of(f"{i}", "truth", [learned + (1 / 16 if i % 2 else 1 / 4)])
    starts = [("s", f"{i}") for i in range(8)]
    sel = paper_selection(rows, starts)
    assert sel["lowest_learned"] == starts[:6]
    # Even starts have the 1/4 gap, then the odd ones (1/16) in name order.
    assert sel["largest_truth_gap"] == [("s", "0"), ("s", "2"), ("s", "4"), ("s", "6"),
                                        ("s", "1"), ("s", "3")]
    text, fig = table2(rows, 200)
    chosen = fig["selection"]["lowest_learned"]
    assert chosen["starts"] == [f"s/{i}" for i in range(6)]
    # gated − learned per start: (i / 128 + 0) / 2, pooled over starts 0..5.
    assert chosen["mean"] == pytest.approx(np.mean([i / 256 for i in range(6)]))
    assert chosen["placebo"]["mean"] == pytest.approx(0.0)
    assert "Selection (a): s/0, s/1, s/2, s/3, s/4, s/5." in text
    no_truth = [r for r in rows if r["condition"] != "truth"]
    assert paper_selection(no_truth, starts)["largest_truth_gap"] is None
    text, fig = table2(no_truth, 200)
    assert fig["selection"]["largest_truth_gap"] is None and "no truth runs" in text


def test_table2_without_gated_runs_says_so():
    text, fig = table2(runs_of("a", "learned", [0.5, 0.6]) + runs_of("a", "obs", [0.5]), 200)
    assert "nothing to compare" in text and fig == {"starts": {}}


# ----------------------------------------------------------------------------- failures

def test_failure_modes_total_the_new_fields_and_dash_what_is_missing():
    new = dict(collisions=2, collisions_planner_fault=1, collisions_unseen=1, stuck_steps=0,
               min_clearance_m=0.3, fp_gain_share=0.2, rejected_by_fp=4)
    rows = [run("a", "learned", 0, 0.5, **new),
            run("a", "learned", 1, 0.5, **{**new, "collisions_unseen": 0, "stuck_steps": 5,
                                           "min_clearance_m": 0.1, "fp_gain_share": 0.4}),
            run("a", "obs", 0, 0.5, collisions=1, min_clearance_m=float("nan"))]  # old run
    text, fig = failure_modes(rows, ("obs", "learned"))
    learned = fig["learned"]
    assert learned["collisions_planner_fault"] == 2
    assert learned["collisions_planner_fault_runs"] == 2
    assert learned["collisions_unseen"] == 1 and learned["collisions_unseen_runs"] == 1
    assert learned["stuck_steps"] == 5 and learned["stuck_steps_runs"] == 1
    assert learned["min_clearance_m_median"] == pytest.approx(0.2)
    assert learned["fp_gain_share_mean"] == pytest.approx(0.3)
    assert learned["rejected_by_fp"] == 8
    assert "| Learned (abs.) | 2 | 4 (2 runs) | 2 (2 runs) | 1 (1 run) | 5 (1 run) | 0.20 | " \
           "0.30 | 8 |" in text
    assert "| Obs. only | 1 | 1 (1 run) | — | — | — | — | — | — |" in text
    assert fig["obs"]["collisions_unseen"] is None


def test_robustness_drops_every_pair_with_a_stuck_or_colliding_run():
    rows = (runs_of("a", "learned", [0.5, 0.6, 0.7])
            + runs_of("a", "gated", [0.6, 0.7, 0.8])            # +0.1 in every pair
            + [run("b", "learned", 0, 0.2, stuck_steps=40),       # stuck: its pair goes
               run("b", "learned", 1, 0.8), run("b", "learned", 2, 0.8),
               run("b", "gated", 0, 0.9), run("b", "gated", 1, 0.8),
               run("b", "gated", 2, 0.7, collisions=2)]          # collided: its pair goes
            + [run("c", "learned", 0, 0.3, stuck_steps=5), run("c", "gated", 0, 0.9)])
    for r in rows:
        r.setdefault("stuck_steps", 0)
        r.setdefault("collisions", 0)
    text, fig = robustness(rows, ("learned", "gated"), resamples=200)
    g = fig["gated"]
    # Every pair: a +0.1, b mean(+0.7, 0, -0.1), c +0.6; clean: a +0.1, b 0 (its r1 alone).
    assert g["every_pair"]["mean"] == pytest.approx((0.1 + 0.2 + 0.6) / 3)
    assert g["clean_pairs"]["mean"] == pytest.approx((0.1 + 0.0) / 2)
    assert g["clean_pairs"]["n"] == 2 and (g["pairs"], g["pairs_kept"]) == (7, 4)
    assert "| 2 of 3 | 4 of 7 |" in text
    # The placebo keeps the clean learned runs: a r1 − mean(r0, r2) = 0; b (r1, r2) 0; c none.
    p = fig["placebo"]
    assert p["clean_pairs"]["mean"] == pytest.approx(0.0) and p["clean_pairs"]["n"] == 2
    assert (p["learned_runs"], p["learned_runs_kept"]) == (7, 5)
    # Runs that lack the counts (written before they existed) are not taken as clean.
    del rows[0]["stuck_steps"]
    text, fig = robustness(rows, ("learned", "gated"), resamples=200)
    assert fig == {} and text.startswith("Not computed")


# ----------------------------------------------------------------------------- write_tables

def _metrics(seed: int, coverage: list[float], new_fields: bool) -> dict:
    m = {"seed": seed, "platform": "flyer", "steps": len(coverage) - 1, "coverage": coverage,
         "final_coverage": coverage[-1], "auc": float(np.mean(coverage)), "collisions": 0,
         "path_length_m": 1.0, "wall_s": 1.0, "median_step_s": 0.1, "min_clearance_m": 0.5,
         "median_stage_s": {"plan": 0.05}}
    if new_fields:
        m.update(collisions_planner_fault=0, collisions_unseen=1, stuck_steps=2,
                 fp_gain_share=0.1, rejected_by_fp=3)
    return m


def test_write_tables_writes_the_new_columns_and_figures(tmp_path: Path):
    cfg = StudyConfig(scenes=("s",), starts=("a", "b"), conditions=("learned", "gated", "truth"),
                      reps=3, steps=2, bootstrap=200, out=tmp_path)
    specs = run_specs(cfg)
    for spec in specs:
        d = tmp_path / "runs" / spec.id
        d.mkdir(parents=True)
        final = {"learned": 0.5, "gated": 0.55, "truth": 0.9}[spec.condition] + 0.01 * spec.rep
        if spec.condition == "gated" and spec.rep == 0:
            final = 0.5                                   # bit-identical to its learned twin
        coverage = [0.0, final / 2, final]
        (d / "metrics.json").write_text(json.dumps(_metrics(spec.rep, coverage,
                                                            spec.start == "a")))
    (tmp_path / "study.json").write_text(json.dumps({"settings": {}, "sessions": []}))
    summary = write_tables(cfg, specs, tmp_path)

    with open(tmp_path / "runs.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 18
    for field in ("collisions_planner_fault", "collisions_unseen", "stuck_steps",
                  "min_clearance_m", "fp_gain_share", "rejected_by_fp"):
        assert field in rows[0], field
    by_start = {r["start"]: r for r in rows if r["condition"] == "learned"}
    assert by_start["a"]["rejected_by_fp"] == "3" and by_start["b"]["rejected_by_fp"] == ""

    # Keys other code reads are kept, and the new figures are there.
    assert summary["table1"]["gated"]["All"]["final_coverage"]["n"] == 2
    assert summary["table1"]["placebo"]["All"]["final_coverage"]["mean"] == pytest.approx(0.0)
    assert summary["table2"]["All starts"]["mean"] == pytest.approx((0.0 + 0.05 + 0.05) / 3)
    assert summary["table2"]["starts"]["s/a"]["p_holm"] == pytest.approx(1.0)
    assert summary["table2"]["identical"] == {"runs": 2, "of": 6}
    assert summary["table2"]["sign_test"]["improve"] == 2
    assert summary["table2"]["selection"]["largest_truth_gap"]["starts"] == ["s/a", "s/b"]
    # Half the runs lack the new counts: the totals are not made up from the other half.
    assert summary["failure_modes"]["learned"]["stuck_steps"] is None
    assert summary["failure_modes"]["learned"]["min_clearance_m_median"] == 0.5
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    table = (tmp_path / "table1.md").read_text()
    assert PLACEBO_LABEL in table and "## Failure modes per condition" in table
    assert "## Without the runs that were stuck or collided" in table
    assert summary["robustness"] == {} and "Not computed" in table  # half lack stuck_steps
    assert "Bit-identical gated runs" in (tmp_path / "table2.md").read_text()

    # A committed study keeps runs.csv and coverage_curves.csv, not its runs: the tables
    # rewritten from those two files are the tables written from the runs.
    again = tmp_path / "committed"
    again.mkdir()
    for name in ("runs.csv", "coverage_curves.csv", "study.json"):
        (again / name).write_bytes((tmp_path / name).read_bytes())
    assert write_tables(cfg, specs, again, loaded=rows_from_csv(again)) == summary
    for name in ("runs.csv", "coverage_curves.csv", "table1.md", "table2.md"):
        assert (again / name).read_text() == (tmp_path / name).read_text(), name
    with pytest.raises(ConfigError, match="--tables-only: .*coverage_curves.csv missing"):
        rows_from_csv(tmp_path / "runs")
