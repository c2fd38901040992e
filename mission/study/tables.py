"""The study's outputs from its finished runs: runs.csv, the paper's two tables with their
statistics, coverage plots and summary.json (see :mod:`mission.study.runner`).

The statistics, and why they are formed this way:

- **Pairing.** Repetition r of every condition runs with seed r, so every delta is a
  condition's run r minus the `learned` run of the same scene, start and repetition r (the
  paper's paired changes). Per start, the effect is the mean of those deltas over the
  repetitions both conditions have (:func:`per_start_effects`).
- **The unit is the start.** The repetitions of one start are not independent draws from the
  population of starts, so every pooled cell is the mean of the per-start effects over starts,
  and its percentile 95% interval comes from a bootstrap that resamples starts with
  replacement (fixed seed). The `learned` row is absolute: its runs' mean per start, then the
  mean over starts.
- **Strata.** Low and High follow the learned baseline's mean final coverage over the
  repetitions of each start (:func:`strata`): Low below 0.75, High above 0.85, as in the paper.
- **The placebo** (:func:`placebo_effects`) is the noise floor of every paired row: the same
  condition against itself. Per start, the learned runs are split into two disjoint halves by a
  fixed rule, odd positions against even positions in repetition order, and the placebo is
  mean(odd) − mean(even); with 3 repetitions r1 − mean(r0, r2). With fewer than 2 repetitions
  it is undefined ("—"). It is pooled over starts like any other row. Splitting halves (and
  not comparing every repetition with repetition 0) keeps repetition 0's luck out of it.
  Repetition r runs with seed r at every start, so a seed's luck shared by many starts moves
  the placebo's pooled mean in a way the bootstrap over starts cannot see.
- **Per start in Table 2**: the paired gated − learned deltas of the R repetitions, their mean,
  and an exact two-sided sign-flip permutation p-value (:func:`signflip_p`: all 2^R sign
  assignments of the deltas; the smallest possible p is 2^(1 − R), 0.25 for R = 3). Across
  starts the p-values are adjusted by Holm (family-wise error, :func:`holm`) and by
  Benjamini–Hochberg (false discovery rate, :func:`bh`).
- **Across starts in Table 2**: a sign test (:func:`sign_test`) on the per-start mean deltas
  (ties dropped, two-sided binomial against p = 1/2), the count of gated runs whose coverage
  curve is bit-identical to their learned twin's (:func:`identical_runs`), and the pooled
  effect on the paper's selection of the learned baseline's largest failures
  (:func:`paper_selection`). That selection is made on the same learned runs the deltas
  subtract, so regression to the mean favours the filter on it.
- **Failure modes** (:func:`failure_modes`, below Table 1): totals over all runs of each
  condition; a count is shown only when every run records it (older runs lack the fields).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib
import numpy as np
from scipy.stats import binomtest, bootstrap, false_discovery_control, permutation_test
from statsmodels.stats.multitest import multipletests

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mission.scoring.metrics import final_coverage, s70  # noqa: E402
from rovergate.conditions import get_condition  # noqa: E402

if TYPE_CHECKING:
    from mission.study.spec import RunSpec, StudyConfig

#: A start of the study: (scene, start name).
Start = tuple[str, str]

LOW, HIGH = 0.75, 0.85
BASELINE = "learned"
FILTER = "gated"
ORACLE = "truth"
#: How many starts the paper's selection of the learned baseline's largest failures holds.
SELECTION_SIZE = 6
#: The level at which a start's adjusted p-value is marked.
ALPHA = 0.05
#: Up to this many repetitions the sign-flip test enumerates every sign assignment.
EXACT_SIGNFLIP_MAX_REPS = 16
LABELS = {"obs": "Obs. only", "learned-fp": "Learned − FP†", "learned": "Learned (abs.)",
          "learned+fn": "Learned + FN†", "truth": "Ground truth†", "gated": "Obs.-gated filter",
          "gated-ray": "Gate, ray-consistent",
          "gated-ray-inf": "Gate, ray + beyond range", "gated-pose": "Gate, pose-aware",
          "gated-split": "Gate, split channels"}
PLACEBO_LABEL = "Placebo (learned vs learned)"
STAGES = ("render", "integrate", "gate", "traverse", "plan", "execute")
#: The hazards the rover's traversability layer refuses motions for (planner/traversability.py).
HAZARD_KINDS = ("unknown", "wheel-drop", "tilt", "belly")
#: Table 1's metrics: (runs.csv column, heading, digits).
METRICS = (("final_coverage", "ΔC_T", 3), ("auc", "ΔAUC", 3), ("s70", "ΔS70", 1))
#: Count fields of metrics.json for the failure modes (absent in older runs: read with .get).
FAILURE_COUNTS = (("collisions", "collisions, all"),
                  ("collisions_planner_fault", "collisions, planner fault"),
                  ("collisions_unseen", "collisions, unseen geometry"),
                  ("stuck_steps", "stuck steps"))


def bootstrap_ci(values: np.ndarray, resamples: int, seed: int = 0) -> tuple[float, float]:
    """Percentile 95% interval of the mean of ``values`` under resampling with replacement
    (:func:`scipy.stats.bootstrap`, one batch of ``resamples`` draws from a generator seeded
    ``seed``)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0:
        return float("nan"), float("nan")
    if len(v) == 1 or np.all(v == v[0]):  # nothing to resample: the interval is the value
        return float(v[0]), float(v[0])
    ci = bootstrap((v,), np.mean, n_resamples=resamples, method="percentile",
                   confidence_level=0.95, rng=np.random.default_rng(seed),
                   vectorized=True).confidence_interval
    return float(ci.low), float(ci.high)


def mean_of(x) -> float | None:
    x = [v for v in x if v is not None]
    return float(np.mean(x)) if x else None


def _kj(j: float | None) -> float | None:
    return None if j is None else j / 1000


def load_rows(specs: list[RunSpec], runs_dir: Path) -> tuple[list[dict], dict[str, list]]:
    """One row per finished run (with S70 against its learned baseline), and the curves."""
    metrics = {}
    for s in specs:
        path = runs_dir / s.id / "metrics.json"
        if path.exists():
            metrics[s] = json.loads(path.read_text())
    baseline = {(s.scene, s.start, s.rep): final_coverage(m["coverage"])
                for s, m in metrics.items() if s.condition == BASELINE}
    rows, curves = [], {}
    for s, m in metrics.items():
        base = baseline.get((s.scene, s.start, s.rep))
        step, reached = s70(m["coverage"], base) if base is not None else (None, None)
        held = m.get("suppressed_per_step") or []
        stage = m.get("median_stage_s", {})
        rows.append({
            "scene": s.scene, "start": s.start, "condition": s.condition, "rep": s.rep,
            "seed": m["seed"], "platform": m["platform"], "profile": s.profile or "nominal",
            "steps": m["steps"],
            "final_coverage": m["final_coverage"], "auc": m["auc"], "s70": step,
            "s70_reached": reached, "collisions": m["collisions"],
            "path_length_m": m["path_length_m"],
            "predicted_per_step": mean_of(m.get("predicted_points_per_step") or [None]),
            "suppressed_per_step": (mean_of(held) if get_condition(s.condition).withholds
                                    else None),
            "suppressed_fp_share": m.get("suppressed_fp_share"),
            "suppression_recall": m.get("suppression_recall"),
            "wrongly_withheld_per_step": (mean_of(m.get("wrongly_withheld_per_step") or [None])
                                          if get_condition(s.condition).withholds else None),
            "predicted_fp_per_step": mean_of(m.get("predicted_fp_per_step") or [None]),
            "wall_s": m["wall_s"], "median_step_s": m["median_step_s"],
            **{f"{k}_s": stage.get(k) for k in STAGES},
            # Failure modes; runs written before these keys existed lack them (None, "—").
            "collisions_planner_fault": m.get("collisions_planner_fault"),
            "collisions_unseen": m.get("collisions_unseen"),
            "stuck_steps": m.get("stuck_steps"),
            "min_clearance_m": m.get("min_clearance_m"),
            **{f"refused_{k.replace('-', '_')}": (m.get("refused_by_hazard") or {}).get(k)
               for k in HAZARD_KINDS},
            "backouts": m.get("backouts"),
            "stays": (m["plan_reasons"].get("stay", 0) if m.get("plan_reasons") is not None
                      else None),
            "fp_gain_share": m.get("fp_gain_share"),
            "rejected_by_fp": m.get("rejected_by_fp"),
            # Costs (mission/scoring/energy.py); runs written before them lack them.
            "cpu_s": m.get("cpu_s"), "peak_rss_mb": m.get("peak_rss_mb"),
            "energy_drive_kj": _kj((m.get("energy_j") or {}).get("drive_j")),
            "energy_compute_kj": _kj((m.get("energy_j") or {}).get("compute_j")),
            "coverage": m["coverage"],
        })
        curves.setdefault(s.condition, []).append(m["coverage"])
    rows.sort(key=lambda r: (r["scene"], r["start"], r["condition"], r["rep"]))
    return rows, curves


def _value(text: str):
    """A runs.csv cell as load_rows wrote it: empty is None, then bool, int, float, text."""
    if text == "":
        return None
    if text in ("True", "False"):
        return text == "True"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def rows_from_csv(out: Path) -> tuple[list[dict], dict[str, list]]:
    """:func:`load_rows`'s rows and curves read back from ``out/runs.csv`` and
    ``out/coverage_curves.csv`` (a committed study's, whose run directories are not kept). The
    curves come back with the 5 decimals the CSV holds; the metrics at full precision."""
    from rovergate.errors import ConfigError
    paths = [Path(out) / "runs.csv", Path(out) / "coverage_curves.csv"]
    if missing := [str(p) for p in paths if not p.is_file()]:
        raise ConfigError(f"--tables-only: {', '.join(missing)} missing; it rewrites the "
                          "tables of a finished study from those files")
    with open(paths[1], newline="") as f:
        curves_by_run = {(r["scene"], r["start"], r["condition"], int(r["rep"])):
                         [float(v) for k, v in r.items() if k[:1] == "c" and k[1:].isdigit()]
                         for r in csv.DictReader(f)}
    rows, curves = [], {}
    with open(paths[0], newline="") as f:
        for r in csv.DictReader(f):
            row = {k: (v if k in ("scene", "start", "condition", "platform", "profile")
                       else _value(v)) for k, v in r.items()}
            row["coverage"] = curves_by_run[(row["scene"], row["start"], row["condition"],
                                             row["rep"])]
            rows.append(row)
            curves.setdefault(row["condition"], []).append(row["coverage"])
    return rows, curves


# ----------------------------------------------------------------------------- statistics

def start_of(row: dict) -> Start:
    """The unit of the study's statistics: the start (scene, start name)."""
    return row["scene"], row["start"]


def _runs(rows: list[dict], condition: str, key=start_of) -> dict[Start, dict[int, dict]]:
    """The runs of one condition, by unit (``key``, default the start) and repetition."""
    out: dict[Start, dict[int, dict]] = {}
    for r in rows:
        if r["condition"] == condition:
            out.setdefault(key(r), {})[r["rep"]] = r
    return out


def paired_deltas(rows: list[dict], condition: str, metric: str, reference: str = BASELINE,
                  key=start_of) -> dict[Start, dict[int, float]]:
    """Per start (or unit: ``key``) and repetition r: ``metric`` of the condition's run r
    minus that of the ``reference`` (learned) run r (same seed). Repetitions missing either
    run, or the metric, are left out."""
    base = _runs(rows, reference, key)
    out = {}
    for k, runs in _runs(rows, condition, key).items():
        twins = base.get(k, {})
        d = {r: run[metric] - twins[r][metric] for r, run in sorted(runs.items())
             if r in twins and run.get(metric) is not None
             and twins[r].get(metric) is not None}
        if d:
            out[k] = d
    return out


def per_start_effects(rows: list[dict], condition: str, metric: str,
                      reference: str = BASELINE, key=start_of) -> dict[Start, float]:
    """Per start (or unit: ``key``): the mean over repetitions of the paired deltas
    (condition − ``reference``, learned); for the reference itself, the absolute mean of its
    runs."""
    if condition == reference:
        means = {k: mean_of(run.get(metric) for run in runs.values())
                 for k, runs in _runs(rows, reference, key).items()}
        return {k: m for k, m in means.items() if m is not None}
    return {k: float(np.mean(list(d.values())))
            for k, d in paired_deltas(rows, condition, metric, reference, key).items()}


def placebo_effects(rows: list[dict], metric: str, key=start_of
                    ) -> dict[Start, float | None]:
    """Per start: the learned condition against itself, mean(odd) − mean(even).

    The learned runs having ``metric`` are taken in repetition order and split by position:
    positions 1, 3, ... against positions 0, 2, ... (with repetitions 0, 1, 2: r1 − mean(r0,
    r2)). The split is fixed before looking at any number. None where a start has fewer than
    two learned runs. ``key``: the unit, default the start."""
    out: dict[Start, float | None] = {}
    for k, runs in _runs(rows, BASELINE, key).items():
        v = [runs[r][metric] for r in sorted(runs) if runs[r].get(metric) is not None]
        out[k] = float(np.mean(v[1::2]) - np.mean(v[0::2])) if len(v) >= 2 else None
    return out


def strata(rows: list[dict]) -> dict[str, list[Start]]:
    """All starts with learned runs, and the Low and High strata by the learned baseline's
    final coverage averaged over the repetitions of each start."""
    learned = per_start_effects(rows, BASELINE, "final_coverage")
    starts = sorted(learned)
    return {"All": starts,
            "Low": [k for k in starts if learned[k] < LOW],
            "High": [k for k in starts if learned[k] > HIGH]}


def signflip_p(deltas: list[float] | np.ndarray) -> float:
    """Two-sided p-value of an exact paired sign-flip permutation test of mean(deltas) = 0
    (:func:`scipy.stats.permutation_test` on one sample, whose permutations flip signs).

    Under the null of no effect each paired delta is as likely positive as negative, so every
    one of the 2^R sign assignments is equally likely; p is the share of them whose mean is as
    far from 0 as the observed one (the null is symmetric, so twice the smaller tail; the
    observed assignment is among them, so p >= 2^(1 − R)). Beyond EXACT_SIGNFLIP_MAX_REPS
    deltas, 2^16 random assignments (fixed seed) stand in for all."""
    d = np.asarray(deltas, dtype=np.float64)
    if len(d) == 0:
        return float("nan")
    exact = len(d) <= EXACT_SIGNFLIP_MAX_REPS
    result = permutation_test((d,), np.mean, permutation_type="samples", vectorized=True,
                              n_resamples=np.inf if exact else 2 ** 16,
                              alternative="two-sided", rng=np.random.default_rng(0))
    return float(result.pvalue)


def holm(p: list[float] | np.ndarray) -> np.ndarray:
    """Holm's step-down adjusted p-values, in the order given (statsmodels' multipletests):
    the i-th smallest p is multiplied by (m − i + 1), then made non-decreasing in that order
    and capped at 1."""
    p = np.asarray(p, dtype=np.float64)
    return multipletests(p, method="holm")[1] if len(p) else p


def bh(p: list[float] | np.ndarray) -> np.ndarray:
    """Benjamini–Hochberg adjusted p-values (false discovery rate), in the order given."""
    p = np.asarray(p, dtype=np.float64)
    return false_discovery_control(p, method="bh") if len(p) else p


def sign_test(effects: list[float]) -> dict:
    """How many starts improve (effect > 0), worsen (< 0) or tie (== 0), and the two-sided
    binomial p-value of the split of the untied ones against 1/2 (no effect)."""
    up = sum(1 for e in effects if e > 0)
    down = sum(1 for e in effects if e < 0)
    untied = up + down
    p = binomtest(up, untied, 0.5).pvalue if untied else 1.0
    return {"improve": up, "worsen": down, "tie": len(effects) - untied,
            "expected_improve": untied / 2, "p": float(p)}


def identical_runs(rows: list[dict], condition: str = FILTER) -> dict[Start, tuple[int, int]]:
    """Per start: (runs of ``condition`` whose coverage curve equals, bit for bit, that of
    the learned run of the same repetition, such runs compared). Rows without curves (as
    runs.csv holds them) are not compared."""
    base = _runs(rows, BASELINE)
    out = {}
    for k, runs in _runs(rows, condition).items():
        pairs = [(run["coverage"], base[k][r]["coverage"]) for r, run in runs.items()
                 if r in base.get(k, {}) and run.get("coverage") is not None
                 and base[k][r].get("coverage") is not None]
        if pairs:
            out[k] = (sum(1 for a, b in pairs if list(a) == list(b)), len(pairs))
    return out


def paper_selection(rows: list[dict], starts: list[Start], size: int = SELECTION_SIZE
                    ) -> dict[str, list[Start] | None]:
    """The paper's selection of the learned baseline's largest failures, among ``starts``:
    ``lowest_learned``, the ``size`` starts of lowest mean learned C_T, and
    ``largest_truth_gap``, those of largest mean paired (truth − learned) C_T (None without
    truth runs). Ties go to the start named first."""
    learned = per_start_effects(rows, BASELINE, "final_coverage")
    gap = per_start_effects(rows, ORACLE, "final_coverage")
    lowest = sorted((k for k in starts if k in learned), key=lambda k: (learned[k], k))
    largest = sorted((k for k in starts if k in gap), key=lambda k: (-gap[k], k))
    return {"lowest_learned": lowest[:size], "largest_truth_gap": largest[:size] or None}


# ----------------------------------------------------------------------------- formatting

def start_name(k: Start) -> str:
    return f"{k[0]}/{k[1]}"


def fmt(v: float | None, signed: bool, digits: int) -> str:
    if v is None or not np.isfinite(v):
        return "—"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def fmt_p(p: float | None) -> str:
    if p is None or not np.isfinite(p):
        return "—"
    return f"{p:.2f}" if p >= 0.01 else f"{p:.1e}"


def pooled_cell(values: list[float], signed: bool, digits: int, resamples: int) -> tuple[str, dict]:
    """A pooled cell: the mean of ``values`` (one per start) and its bootstrap 95% CI."""
    if not values:
        return "—", {"mean": None, "ci95": None, "n": 0}
    m = float(np.mean(values))
    lo, hi = bootstrap_ci(np.array(values), resamples)
    text = f"{fmt(m, signed, digits)} [{fmt(lo, signed, digits)}, {fmt(hi, signed, digits)}]"
    return text, {"mean": m, "ci95": [lo, hi], "n": len(values)}


def pooled_over(effects: dict[Start, float | None], keys: list[Start], signed: bool, digits: int,
            resamples: int) -> tuple[str, dict]:
    return pooled_cell([effects[k] for k in keys if effects.get(k) is not None], signed, digits,
                 resamples)


def _span(counts: set[int]) -> str:
    if not counts:
        return "0"
    lo, hi = min(counts), max(counts)
    return str(lo) if lo == hi else f"{lo}–{hi}"


# ----------------------------------------------------------------------------- Table 1

def table1(rows: list[dict], conditions: tuple[str, ...], resamples: int, steps: int
           ) -> tuple[str, dict]:
    """The paper's Table 1 over every repetition: learned absolute, the other conditions as
    the mean over starts of their per-start mean paired change, and the placebo row."""
    groups = strata(rows)
    lines = ["| Planner occupancy | Group | ΔC_T | ΔAUC | ΔS70 |", "|---|---|---|---|---|"]
    figures: dict = {}
    paired_reps = {}
    for c in conditions:
        runs = _runs(rows, c)
        effects = {m: per_start_effects(rows, c, m) for m, _, _ in METRICS}
        if c == BASELINE:
            paired_reps[c] = {len(v) for v in runs.values()}
        else:
            paired_reps[c] = {len(d) for d in paired_deltas(rows, c, "final_coverage").values()}
        for g, keys in groups.items():
            cells, fig = [], {}
            for metric, _, digits in METRICS:
                text, fig[metric] = pooled_over(effects[metric], keys, c != BASELINE, digits,
                                            resamples)
                cells.append(text)
            fig["s70_unreached"] = sum(1 for k in keys for run in runs.get(k, {}).values()
                                       if run.get("s70_reached") is False)
            figures.setdefault(c, {})[g] = fig
            name = LABELS.get(c, c) if g == "All" else ""
            lines.append(f"| {name} | {g} (n={fig['final_coverage']['n']}) | "
                         + " | ".join(cells) + " |")
    placebo = {m: placebo_effects(rows, m) for m, _, _ in METRICS}
    for g, keys in groups.items():
        cells, fig = [], {}
        for metric, _, digits in METRICS:
            text, fig[metric] = pooled_over(placebo[metric], keys, True, digits, resamples)
            cells.append(text)
        figures.setdefault("placebo", {})[g] = fig
        name = PLACEBO_LABEL if g == "All" else ""
        lines.append(f"| {name} | {g} (n={fig['final_coverage']['n']}) | "
                     + " | ".join(cells) + " |")
    n_unreached = {c: figures[c]["All"]["s70_unreached"] for c in conditions}
    learned_reps = paired_reps.get(BASELINE, set())
    notes = [
        "",
        "n counts starts, the unit of every interval. Learned row: absolute, the mean of each "
        "start's learned runs, then over starts. Other rows: per start, the mean over "
        "repetitions r of (condition run r − learned run r, same seed), then the mean over "
        "starts. Brackets: bootstrap 95% CI resampling starts "
        f"({resamples} resamples). Repetitions per start: "
        + ", ".join(f"{LABELS.get(c, c)} {_span(paired_reps[c])}" for c in conditions)
        + f". Lower ΔS70 is faster. Low: mean learned C_T over the repetitions < {LOW}; "
        f"High: > {HIGH}. † ground-truth oracle (diagnosis only).",
        f"{PLACEBO_LABEL}: the noise floor, learned against itself. Per start, the learned "
        "runs in repetition order are split into two fixed halves, odd positions against even "
        "ones, and the row gives mean(odd) − mean(even) (with 3 repetitions: r1 − mean(r0, "
        "r2)), pooled over starts as above; with fewer than 2 learned repetitions it is "
        f"\"—\" (here {_span(learned_reps)} learned repetitions per start). A condition "
        "whose interval sits inside the placebo's spread is within run-to-run noise. The "
        "halves differ in seed, so per start the placebo is, if anything, wider than the null "
        "of a same-seed paired row (with 3 repetitions it sets one run against the mean of "
        "two). Repetition r runs with seed r at every start, so a seed that is lucky at many "
        "starts shifts the placebo at all of them, which the bootstrap over starts does not "
        "see: a placebo interval away from zero points to such a seed effect, or to chance. "
        "Its ΔS70 takes each learned run's own C_T as the 70% reference.",
        f"S70 not reached within {steps} steps counts as {steps + 1}; runs that never reached "
        "it: " + ", ".join(f"{LABELS.get(c, c)} {n}" for c, n in n_unreached.items()) + ".",
    ]
    return "\n".join(lines + notes) + "\n", figures


def failure_modes(rows: list[dict], conditions: tuple[str, ...]) -> tuple[str, dict]:
    """Table 1's companion: per condition, over all its runs, the collisions (all, planner
    fault, unseen geometry) and stuck steps with the runs that had any, the median of the
    runs' minimum clearance, the mean share of the chosen viewpoint's gain owed to oracle false
    positives, and the candidates rejected because of them. A count is shown only when every
    run reports it (runs from before a field existed make it "—")."""
    heads = [h for _, h in FAILURE_COUNTS]
    lines = ["| Planner occupancy | runs | " + " | ".join(heads)
             + " | min clearance, median (m) | FP gain share, mean | rejected by FP |",
             "|---|---|" + "---|" * (len(heads) + 3)]
    figures: dict = {}
    for c in conditions:
        runs = [r for r in rows if r["condition"] == c]
        fig: dict = {"runs": len(runs)}
        cells = []
        for key, _ in FAILURE_COUNTS:
            values = [r.get(key) for r in runs]
            if runs and all(v is not None for v in values):
                fig[key] = int(sum(values))
                fig[f"{key}_runs"] = sum(1 for v in values if v > 0)
                n = fig[f"{key}_runs"]
                cells.append(f"{fig[key]} ({n} run{'' if n == 1 else 's'})")
            else:
                fig[key] = fig[f"{key}_runs"] = None
                cells.append("—")
        clearance = [r["min_clearance_m"] for r in runs
                     if r.get("min_clearance_m") is not None
                     and math.isfinite(r["min_clearance_m"])]
        fig["min_clearance_m_median"] = float(np.median(clearance)) if clearance else None
        fig["fp_gain_share_mean"] = mean_of(v for r in runs if (v := r.get("fp_gain_share"))
                                          is not None and math.isfinite(v))
        rejected = [r.get("rejected_by_fp") for r in runs]
        fig["rejected_by_fp"] = (int(sum(rejected)) if runs
                                 and all(v is not None for v in rejected) else None)
        cells += [fmt(fig["min_clearance_m_median"], False, 2),
                  fmt(fig["fp_gain_share_mean"], False, 2),
                  "—" if fig["rejected_by_fp"] is None else str(fig["rejected_by_fp"])]
        figures[c] = fig
        lines.append(f"| {LABELS.get(c, c)} | {len(runs)} | " + " | ".join(cells) + " |")
    notes = ["", "Totals over every run of the condition (all starts and repetitions), with the "
             "runs that had any in brackets. Collisions, all: `collisions`; planner fault "
             "(the map held an obstacle within the planner's margin of the contact) and "
             "unseen geometry (it did not): `collisions_planner_fault`, `collisions_unseen`; "
             "stuck steps "
             "(under 0.5 m of net progress over the last 10 steps): `stuck_steps`. "
             "Min clearance: the median over runs of each run's `min_clearance_m`. FP gain "
             "share: per step, the share of the chosen viewpoint's rendered gain that came "
             "from oracle false positives, averaged over steps, then over runs (0 in "
             "conditions whose map holds no prediction). Rejected by FP: candidate viewpoints "
             "rejected as infeasible whose occupancy check failed only because of oracle false "
             "positives, summed over runs. \"—\": not recorded by these runs."]
    return "\n".join(lines + notes) + "\n", figures


#: The rover's driving targets (issue 26): a run stuck this many steps or more fails, and so
#: does one that drove less than this far.
MAX_STUCK_STEPS = 10
MIN_DRIVEN_M = 20.0


def driving(rows: list[dict], conditions: tuple[str, ...]) -> tuple[str, dict]:
    """How the platform drove, per condition: collisions, stuck steps (as a share of all
    steps, and the runs stuck more than ``MAX_STUCK_STEPS``), metres driven (the least, and
    the runs under ``MIN_DRIVEN_M``), the closest approach to the true scene, the motions the
    rover's traversability layer refused by hazard, its backouts, and the layer's time per
    step (the median of the runs' medians)."""
    lines = ["| Planner occupancy | runs | collisions (planner fault / unseen) | stuck steps "
             f"(share) | runs stuck > {MAX_STUCK_STEPS} | least driven (m) | runs under "
             f"{MIN_DRIVEN_M:.0f} m | closest approach (m) | refused: unknown / wheel drop / "
             "tilt / belly | backouts | stays | layer (ms/step) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    figures: dict = {}
    for c in conditions:
        runs = [r for r in rows if r["condition"] == c]
        if not runs:
            continue
        steps = sum(r["steps"] for r in runs)
        stuck = [r.get("stuck_steps") or 0 for r in runs]
        driven = [r["path_length_m"] for r in runs]
        clear = [r["min_clearance_m"] for r in runs if r.get("min_clearance_m") is not None
                 and math.isfinite(r["min_clearance_m"])]
        refused = {k: sum(r.get(f"refused_{k.replace('-', '_')}") or 0 for r in runs)
                   for k in HAZARD_KINDS}
        layer = [r["traverse_s"] for r in runs if r.get("traverse_s") is not None]
        fig = {"runs": len(runs), "collisions": int(sum(r["collisions"] for r in runs)),
               "stuck_steps": int(sum(stuck)), "stuck_share": sum(stuck) / steps if steps
               else None, "runs_stuck_over_max": sum(v > MAX_STUCK_STEPS for v in stuck),
               "least_driven_m": min(driven), "runs_under_min_driven":
               sum(d < MIN_DRIVEN_M for d in driven),
               "closest_approach_m": min(clear) if clear else None, "refused": refused,
               "backouts": int(sum(r.get("backouts") or 0 for r in runs)),
               "stays": int(sum(r.get("stays") or 0 for r in runs)),
               "collisions_planner_fault": int(sum(r.get("collisions_planner_fault") or 0
                                                   for r in runs)),
               "collisions_unseen": int(sum(r.get("collisions_unseen") or 0 for r in runs)),
               "traverse_ms_median": 1000 * float(np.median(layer)) if layer else None}
        figures[c] = fig
        lines.append(
            f"| {LABELS.get(c, c)} | {len(runs)} | {fig['collisions']} "
            f"({fig['collisions_planner_fault']} / {fig['collisions_unseen']}) | "
            f"{fig['stuck_steps']} "
            f"({100 * (fig['stuck_share'] or 0):.1f}%) | {fig['runs_stuck_over_max']} | "
            f"{fig['least_driven_m']:.1f} | {fig['runs_under_min_driven']} | "
            + fmt(fig["closest_approach_m"], False, 2) + " | "
            + " / ".join(str(refused[k]) for k in HAZARD_KINDS)
            + f" | {fig['backouts']} | {fig['stays']} | "
            + fmt(fig["traverse_ms_median"], False, 1) + " |")
    notes = ["", "Totals over every run of the condition. Stuck: under 0.5 m of net progress "
             "over the last 10 steps. Closest approach: the least clearance between the body "
             "and the true scene over every executed motion of every run (negative: a "
             "touch). Refused: candidate goals and motions the rover's traversability layer "
             "refused, by the first hazard found; backouts: steps the rover backed along the "
             "way it came (planner/traversability.py); stays: steps the planner found no "
             "way to move (the rover's mast then looks around). Collisions by class "
             "(mission/scoring/evaluation.py): a planner fault touched what its map held, unseen "
             "geometry what it did not. The layer's time is the planner's "
             "`traverse` stage: the frames into the height map and the step's masks."]
    return "\n".join(lines + notes) + "\n", figures


def costs(rows: list[dict], conditions: tuple[str, ...]) -> tuple[str, dict]:
    """What the runs cost, per condition, measured in the runs themselves: the median step and
    the median of each run's median gate and planner stage, the CPU seconds and peak memory of a
    run (median and largest), and the energy estimate (mean; mission/scoring/energy.py). "—"
    where the runs do not record it."""
    lines = ["| Planner occupancy | runs | step (ms) | gate (ms) | plan (ms) | CPU per run (s) "
             "| peak memory (MB), median / max | drive energy (kJ) | compute energy (kJ) |",
             "|---|---|---|---|---|---|---|---|---|"]
    figures: dict = {}

    def med(runs, key, scale=1.0):
        v = [r[key] for r in runs if r.get(key) is not None]
        return scale * float(np.median(v)) if v else None

    for c in conditions:
        runs = [r for r in rows if r["condition"] == c]
        if not runs:
            continue
        peak = [r["peak_rss_mb"] for r in runs if r.get("peak_rss_mb") is not None]
        fig = {"runs": len(runs), "step_ms": med(runs, "median_step_s", 1000),
               "gate_ms": med(runs, "gate_s", 1000), "plan_ms": med(runs, "plan_s", 1000),
               "cpu_s": med(runs, "cpu_s"),
               "peak_rss_mb": float(np.median(peak)) if peak else None,
               "peak_rss_mb_max": max(peak) if peak else None,
               "drive_kj": mean_of(r.get("energy_drive_kj") for r in runs),
               "compute_kj": mean_of(r.get("energy_compute_kj") for r in runs)}
        figures[c] = fig
        lines.append(f"| {LABELS.get(c, c)} | {len(runs)} | " + " | ".join(
            fmt(fig[k], False, d) for k, d in (("step_ms", 0), ("gate_ms", 1), ("plan_ms", 0),
                                                ("cpu_s", 1)))
            + f" | {fmt(fig['peak_rss_mb'], False, 0)} / {fmt(fig['peak_rss_mb_max'], False, 0)}"
            + f" | {fmt(fig['drive_kj'], False, 0)} | {fmt(fig['compute_kj'], False, 2)} |")
    notes = ["", "Measured in the study's own runs, every module in one process: step, gate "
             "and plan are the medians over runs of each run's median per step; CPU: user and "
             "system seconds of the whole run; peak memory: the run's process (Linux resets it "
             "per run). Energy (mission/scoring/energy.py): drive = metres driven x 2.7 kJ/m "
             "on the rover (a Mars Exploration Rover's 100 W at 3.7 cm/s; none for the flyer); "
             "compute = CPU seconds x 4.4 W (a server core). A model, not a measurement: "
             "docs/study.md gives its sources and limits."]
    return "\n".join(lines + notes) + "\n", figures


def clean_run(run: dict) -> bool:
    """A run with no stuck step and no collision."""
    return run["stuck_steps"] == 0 and run["collisions"] == 0


def robustness(rows: list[dict], conditions: tuple[str, ...], resamples: int
               ) -> tuple[str, dict]:
    """Table 1's ΔC_T over All starts again, keeping only the clean pairs: repetition r of a
    start counts only if neither the condition's run r nor the learned run r was ever stuck
    or collided (:func:`clean_run`); the placebo keeps the clean learned runs. Not computed
    (a line saying so) when some run lacks either count."""
    if any(r.get("stuck_steps") is None or r.get("collisions") is None for r in rows):
        return ("Not computed: some runs do not record `stuck_steps` or `collisions` (runs "
                "from before those fields existed).\n"), {}
    clean = [r for r in rows if clean_run(r)]
    lines = ["| Planner occupancy | ΔC_T, every pair | ΔC_T, clean pairs only | starts kept "
             "| pairs kept |", "|---|---|---|---|---|"]
    figures: dict = {}
    for c in conditions:
        if c == BASELINE:
            continue
        full = per_start_effects(rows, c, "final_coverage")
        kept = per_start_effects(clean, c, "final_coverage")
        pairs = sum(len(d) for d in paired_deltas(rows, c, "final_coverage").values())
        pairs_kept = sum(len(d) for d in paired_deltas(clean, c, "final_coverage").values())
        t_full, f_full = pooled_over(full, sorted(full), True, 3, resamples)
        t_kept, f_kept = pooled_over(kept, sorted(kept), True, 3, resamples)
        figures[c] = {"every_pair": f_full, "clean_pairs": f_kept, "pairs": pairs,
                      "pairs_kept": pairs_kept}
        lines.append(f"| {LABELS.get(c, c)} | {t_full} | {t_kept} | {len(kept)} of "
                     f"{len(full)} | {pairs_kept} of {pairs} |")
    full_p = placebo_effects(rows, "final_coverage")
    kept_p = placebo_effects(clean, "final_coverage")
    t_full, f_full = pooled_over(full_p, sorted(full_p), True, 3, resamples)
    t_kept, f_kept = pooled_over(kept_p, sorted(kept_p), True, 3, resamples)
    n_clean = sum(1 for r in clean if r["condition"] == BASELINE)
    n_all = sum(1 for r in rows if r["condition"] == BASELINE)
    starts_kept = sum(1 for v in kept_p.values() if v is not None)
    figures["placebo"] = {"every_pair": f_full, "clean_pairs": f_kept,
                          "learned_runs": n_all, "learned_runs_kept": n_clean}
    lines.append(f"| {PLACEBO_LABEL} | {t_full} | {t_kept} | {starts_kept} of "
                 f"{sum(1 for v in full_p.values() if v is not None)} | {n_clean} of {n_all} "
                 "learned runs |")
    notes = ["", "All starts, bootstrap 95% CI resampling starts, as in Table 1. Clean pairs "
             "only: repetition r of a start counts only if neither the condition's run r nor "
             "the learned run r had a stuck step or a collision; a start with no clean pair "
             "drops out. The placebo keeps the learned runs that are clean, split as above "
             "(a start needs two). An effect that Table 1 shows and this column does not may "
             "rest on runs that were stuck or collided. Read it as a check, not as the effect: "
             "being stuck is itself an outcome of the planner-facing map, so keeping only clean "
             "pairs selects on the outcome, and fewer pairs widen the interval."]
    return "\n".join(lines + notes) + "\n", figures


def crossfit_strata(rows: list[dict], condition: str, resamples: int) -> dict:
    """Strata and the paper's selection chosen from some repetitions, effects measured on
    another: for each repetition k, the starts are chosen by the learned runs of the other
    repetitions, and their paired change (``condition`` − learned) is read at repetition k;
    a group's effect is the mean over the folds of its starts' changes. Beside it, the
    in-sample effect (chosen and measured on every repetition). Returns, per group, both
    means and the held-out one's bootstrap interval over starts."""
    deltas = paired_deltas(rows, condition, "final_coverage")
    reps = sorted({r["rep"] for r in rows if r["condition"] == BASELINE})
    out: dict = {}
    if len(reps) < 2 or not deltas:
        return out
    choosers = {
        "Low": lambda rs: strata(rs)["Low"],
        "High": lambda rs: strata(rs)["High"],
        "Selection (a)": lambda rs: paper_selection(rs, strata(rs)["All"])
        ["lowest_learned"],
    }
    everything = per_start_effects(rows, condition, "final_coverage")
    for name, pick in choosers.items():
        held: dict[Start, list[float]] = {}
        for k in reps:
            chosen = pick([r for r in rows if r["rep"] != k])
            for s in chosen:
                if k in deltas.get(s, {}):
                    held.setdefault(s, []).append(deltas[s][k])
        per_start = {s: float(np.mean(v)) for s, v in held.items()}
        text, fig = pooled_over(per_start, sorted(per_start), True, 3, resamples)
        chosen_all = pick(rows)
        itext, fig["in_sample"] = pooled_over(everything, chosen_all, True, 3, resamples)
        fig["text"], fig["in_sample_text"] = text, itext
        out[name] = fig
    return out



def crossfit(rows: list[dict], conditions: tuple[str, ...], resamples: int
             ) -> tuple[str, dict]:
    """Table 1's strata and the paper's selection (a) with the choice held out
    (:func:`crossfit_strata`), beside the same groups chosen and measured on every repetition."""
    lines = ["| Planner occupancy | Group | ΔC_T, chosen on every repetition | ΔC_T, chosen on "
             "the other repetitions | starts |", "|---|---|---|---|---|"]
    figures: dict = {}
    for c in conditions:
        if c == BASELINE:
            continue
        groups = crossfit_strata(rows, c, resamples)
        if not groups:
            continue
        figures[c] = groups
        for i, (g, fig) in enumerate(groups.items()):
            lines.append(f"| {LABELS.get(c, c) if i == 0 else ''} | {g} | "
                         f"{fig['in_sample_text']} | {fig['text']} | {fig['n']} |")
    if not figures:
        return "Not computed: it needs at least 2 learned repetitions.\n", {}
    notes = ["", "The strata and the selection pick starts by their learned runs, and the "
             "deltas subtract those same runs: a start picked for a bad learned run looks "
             "better next time under any condition (regression to the mean). Held out: for "
             "each repetition k, the starts are chosen by the learned runs of the other "
             "repetitions and their paired change is read at repetition k; a start's change "
             "is the mean over the folds that chose it, pooled over those starts (bootstrap "
             "95% CI over starts; starts: how many were chosen in some fold). A group whose "
             "effect shrinks from the first column to the second was, in part, selected. "
             "`rovergate study --select-from DIR --seeds ...` tests the selection on new seeds."]
    return "\n".join(lines + notes) + "\n", figures


# ----------------------------------------------------------------------------- Table 2

def _mean_std(x: np.ndarray) -> str:
    """Mean ± sample std; one value has no std ("—")."""
    return f"{x.mean():.3f} ± " + (f"{x.std(ddof=1):.3f}" if len(x) > 1 else "—")


def table2(rows: list[dict], resamples: int) -> tuple[str, dict]:
    """The paper's Table 2 on every start: learned against gated, mean ± std over the
    repetitions, the mean paired ΔC_T with its sign-flip p-value (raw and Holm-adjusted), and
    the pooled rows, the paper's selection, the sign test and the bit-identical runs."""
    deltas = paired_deltas(rows, FILTER, "final_coverage")
    starts = sorted(deltas)
    if not starts:
        return ("No gated run has a learned twin (same start and repetition): nothing to "
                "compare.\n"), {"starts": {}}
    learned, gated = _runs(rows, BASELINE), _runs(rows, FILTER)
    effect = {k: float(np.mean(list(deltas[k].values()))) for k in starts}
    p_raw = [signflip_p(list(deltas[k].values())) for k in starts]
    p_holm, p_bh = holm(p_raw), bh(p_raw)
    identical = identical_runs(rows)
    placebo = placebo_effects(rows, "final_coverage")
    lines = ["| Start | Learned baseline | Obs.-gated filter | ΔC_T | reps | p | p (Holm) | "
             "identical | withheld / step | true FP share |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    figures: dict = {"starts": {}}
    for i, k in enumerate(starts):
        reps = list(deltas[k])
        lc = np.array([learned[k][r]["final_coverage"] for r in reps])
        gc = np.array([gated[k][r]["final_coverage"] for r in reps])
        held = mean_of(gated[k][r]["suppressed_per_step"] for r in reps)
        share = mean_of(gated[k][r]["suppressed_fp_share"] for r in reps)
        same = identical.get(k)
        mark = " *" if p_holm[i] < ALPHA else ""
        lines.append(f"| {start_name(k)} | {_mean_std(lc)} | {_mean_std(gc)} | "
                     f"{fmt(effect[k], True, 3)} | {len(reps)} | {fmt_p(p_raw[i])} | "
                     f"{fmt_p(p_holm[i])}{mark} | "
                     f"{'—' if same is None else f'{same[0]}/{same[1]}'} | "
                     f"{fmt(held, False, 0)} | {fmt(share, False, 2)} |")
        figures["starts"][start_name(k)] = {
            "learned": lc.tolist(), "gated": gc.tolist(),
            "delta": {"mean": effect[k], "values": [deltas[k][r] for r in reps],
                      "n": len(reps)},
            "p_signflip": p_raw[i], "p_holm": float(p_holm[i]), "p_bh": float(p_bh[i]),
            "placebo": placebo.get(k),
            "identical": None if same is None else {"runs": same[0], "of": same[1]}}

    # Pooled over starts, each beside its placebo (the same starts' learned-vs-learned split).
    # Rows: (label, where in figures, starts); the strata keep their summary.json keys.
    groups = strata(rows)
    selection = paper_selection(rows, starts)
    size = SELECTION_SIZE
    pooled = [
        ("All starts", ("All starts",), starts),
        (f"Low (mean learned C_T < {LOW})", (f"Low (learned C_T < {LOW})",),
         [k for k in groups["Low"] if k in effect]),
        (f"High (mean learned C_T > {HIGH})", (f"High (learned C_T > {HIGH})",),
         [k for k in groups["High"] if k in effect]),
        (f"Selection (a): {size} lowest mean learned C_T", ("selection", "lowest_learned"),
         selection["lowest_learned"]),
        (f"Selection (b): {size} largest truth − learned gap",
         ("selection", "largest_truth_gap"), selection["largest_truth_gap"]),
    ]
    table = ["| Starts | n | ΔC_T gated − learned [95% CI] | placebo learned − learned "
             "[95% CI] |", "|---|---|---|---|"]
    for label, where, keys in pooled:
        if keys is None:  # no truth runs: no selection (b)
            figures.setdefault(where[0], {})[where[-1]] = None
            table.append(f"| **{label}** | 0 | — (no truth runs) | — |")
            continue
        text, fig = pooled_over(effect, keys, True, 3, resamples)
        ptext, fig["placebo"] = pooled_over(placebo, keys, True, 3, resamples)
        if fig["placebo"]["n"] not in (0, len(keys)):
            ptext += f" (n={fig['placebo']['n']})"
        fig["starts"] = [start_name(k) for k in keys]
        if len(where) == 1:
            figures[where[0]] = fig
        else:
            figures.setdefault(where[0], {})[where[1]] = fig
        table.append(f"| **{label}** | {len(keys)} | {text} | {ptext} |")

    tests = sign_test(list(effect.values()))
    pairs = [identical[k] for k in starts if k in identical]
    same_total = (sum(a for a, _ in pairs), sum(b for _, b in pairs)) if pairs else None
    n_holm = int(np.sum(p_holm < ALPHA))
    n_bh = int(np.sum(p_bh < ALPHA))
    figures["sign_test"] = tests
    figures["identical"] = (None if same_total is None
                            else {"runs": same_total[0], "of": same_total[1]})
    figures["significant"] = {"alpha": ALPHA, "holm": n_holm, "bh": n_bh, "starts": len(starts)}

    rep_counts = {len(deltas[k]) for k in starts}
    r_min, r_max, m = min(rep_counts), max(rep_counts), len(starts)
    # The repetitions a start needs before Holm over m starts can reach ALPHA at all.
    r_needed = next(r for r in range(1, 64) if m * 2.0 ** (1 - r) < ALPHA)
    reach = (f"Over {m} starts, Holm can reach {ALPHA} only with R >= {r_needed} "
             "repetitions" + ("; here no single start can, and the pooled rows and the sign "
                              "test are the tests this study can pass." if r_max < r_needed
                              else "."))
    after = [
        "",
        "Pooled over starts (bootstrap 95% CI resampling starts, "
        f"{resamples} resamples), each beside the placebo of the same starts:",
        "",
        *table,
        "",
        *(f"Selection ({n}): " + ", ".join(figures["selection"][g]["starts"]) + "."
          for n, g in (("a", "lowest_learned"), ("b", "largest_truth_gap"))
          if figures["selection"][g] is not None),
        "",
        f"**Sign test over starts** (mean ΔC_T per start): {tests['improve']} improve, "
        f"{tests['worsen']} worsen, {tests['tie']} tie; with no effect "
        f"{tests['expected_improve']:g} of the {tests['improve'] + tests['worsen']} untied "
        f"would be expected to improve; two-sided binomial p = {fmt_p(tests['p'])} "
        "(ties dropped).",
        "",
        "**Bit-identical gated runs**: " + (
            f"{same_total[0]} of {same_total[1]} gated runs have the same coverage curve as "
            "their learned twin (same start and seed): on them the gate changed nothing the "
            "planner acted on, and their delta is exactly 0 (per start: `identical`)."
            if same_total else "— (no coverage curves in these rows)."),
        "",
        "Final coverage, mean ± std over repetitions (seed = repetition). ΔC_T: per start, "
        "the mean of the paired changes (gated − learned, same seed). p: exact two-sided "
        "sign-flip permutation test of those R paired changes (all 2^R sign assignments); its "
        f"smallest possible value is 2^(1 − R), {2.0 ** (1 - r_min):.2f} with R = {r_min}, "
        "and it is what a start gets whose R changes all have one sign: with 3 repetitions, "
        "three gains in three runs are p = 0.25, not a finding. p (Holm): adjusted for the "
        f"{m} starts tested (family-wise); * marks p (Holm) < {ALPHA} ({n_holm} starts; "
        f"Benjamini–Hochberg, in summary.json: {n_bh}). {reach} Low and High: by the mean "
        "learned C_T over the repetitions of each start. Selections (a) and (b) are the "
        "paper's choice of the learned baseline's largest failures; they select on the same "
        "learned runs that the deltas subtract, so regression to the mean favours the filter "
        "there, and the placebo (whose halves were both selected) does not show that bias. "
        "Withheld / step: points the gate withheld per step; true FP share: of those, the "
        "share farther than 0.03 d_scene from the true surface (evaluation only).",
    ]
    return "\n".join(lines + after) + "\n", figures


def plot_curves(curves: dict[str, list], out: Path) -> list[str]:
    names = []
    for c, cs in curves.items():
        fig, ax = plt.subplots(figsize=(6, 4))
        arr = np.array(cs)
        for cov in arr:
            ax.plot(cov, color="steelblue", lw=0.6, alpha=0.35)
        ax.plot(arr.mean(axis=0), color="navy", lw=2.5, label=f"mean of {len(arr)} runs")
        if c != BASELINE and BASELINE in curves:
            ax.plot(np.mean(curves[BASELINE], axis=0), color="darkorange", lw=1.8, ls="--",
                    label="learned (mean)")
        ax.set(xlabel="planning step", ylabel="surface coverage", ylim=(0, 1),
               title=f"{LABELS.get(c, c)}: coverage per step")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right")
        fig.tight_layout()
        name = f"coverage_{c}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        names.append(name)
    return names


def write_runs_csv(rows: list[dict], path: Path) -> None:
    """runs.csv: one row per run, every field but the coverage curve (nothing if no rows)."""
    if not rows:
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[k for k in rows[0] if k != "coverage"],
                           extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def write_tables(cfg: StudyConfig, specs: list[RunSpec], out: Path,
                 platform: str | None = None, sessions: list | None = None,
                 loaded: tuple[list[dict], dict[str, list]] | None = None) -> dict:
    """runs.csv, table1.md (with the failure modes and the robustness check below it),
    table2.md, the plots, coverage_curves.csv and summary.json of the study in ``out``
    (its runs in ``out/runs``; its sessions from ``out/study.json``
    unless given). A cell of a study passes its own directory, platform and the study's
    sessions, and the rows and curves it has read (``loaded``: :func:`load_rows`'s)."""
    rows, curves = loaded or load_rows(specs, out / "runs")
    curves = {c: curves[c] for c in (*cfg.conditions, *curves) if c in curves}  # plots' order
    write_runs_csv(rows, out / "runs.csv")
    t1, f1 = table1(rows, cfg.conditions, cfg.bootstrap, cfg.steps)
    tf, ff = failure_modes(rows, cfg.conditions)
    td, fd = driving(rows, cfg.conditions)
    tr, fr = robustness(rows, cfg.conditions, cfg.bootstrap)
    tx, fx = crossfit(rows, cfg.conditions, cfg.bootstrap)
    tc, fc = costs(rows, cfg.conditions)
    t2, f2 = table2(rows, cfg.bootstrap)
    if platform is None:
        platform = cfg.platform if isinstance(cfg.platform, str) else cfg.platform[0]
    profile = specs[0].profile if specs and specs[0].profile else "nominal"
    header = (f"Platform {platform}, sensing {profile}, {cfg.steps} steps, scenes "
              f"{', '.join(cfg.scenes)}, starts {', '.join(cfg.starts)}.\n\n")
    (out / "table1.md").write_text("# Table 1: controlled occupancy interventions\n\n"
                                   + header + t1 + "\n## Failure modes per condition\n\n"
                                   + tf + "\n## How the platform drove\n\n" + td
                                   + "\n## Without the runs that were stuck or collided\n\n"
                                   + tr + "\n## Strata chosen on other repetitions\n\n" + tx
                                   + "\n## What the runs cost\n\n" + tc)
    (out / "table2.md").write_text("# Table 2: final coverage, learned against the "
                                   "observation-gated filter\n\n" + header + t2)
    plots = plot_curves(curves, out)
    if rows:
        with open(out / "coverage_curves.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["scene", "start", "condition", "rep",
                        *[f"c{t}" for t in range(len(rows[0]["coverage"]))]])
            for r in rows:
                w.writerow([r["scene"], r["start"], r["condition"], r["rep"],
                            *[f"{c:.5f}" for c in r["coverage"]]])
    if sessions is None:
        sessions = json.loads((out / "study.json").read_text())["sessions"]
    stages = {k: float(np.median([r[f"{k}_s"] for r in rows if r[f"{k}_s"] is not None]))
              for k in STAGES if any(r[f"{k}_s"] is not None for r in rows)}
    summary = {
        "runs": len(rows), "expected_runs": len(specs),
        "wall_s": sum(s["wall_s"] for s in sessions),
        "sessions": sessions,
        "run_wall_s_median": float(np.median([r["wall_s"] for r in rows])) if rows else None,
        "run_wall_s_sum": float(sum(r["wall_s"] for r in rows)),
        "median_step_s": float(np.median([r["median_step_s"] for r in rows])) if rows else None,
        "median_stage_s": stages,
        "table1": f1, "failure_modes": ff, "driving": fd, "robustness": fr, "crossfit": fx,
        "costs": fc, "table2": f2,
        "plots": plots,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
