"""The outputs of a study of cells (``rovergate study --preset validation``): every
(platform, sensing profile) cell's own tables, and across them the paper's required validation
(issue 16): coverage against `learned` and against the frustum gate, suppression precision and
recall, true surface wrongly withheld, collisions by class, clearance and gate latency, per
variant and profile.

Statistics, as in :mod:`mission.study.tables`: every delta pairs run r of a condition with run r of
its reference (same seed, scene, start, platform and profile); the unit of every interval is
the start within a cell (scene, start), and pooled over profiles the (profile, scene, start):
per unit the mean over repetitions, then the mean over units, with a bootstrap 95% interval
resampling units. The placebo (learned against itself, odd against even repetitions) is the
noise floor of each cell and of each pooled row.

Suppression precision and recall are pooled as ratios of sums over runs (every withheld point
weighs the same, whichever run it came from): precision = true false positives withheld /
points withheld; recall = true false positives withheld / oracle false positives predicted.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mission.study.tables import (  # noqa: E402
    BASELINE,
    FILTER,
    LABELS,
    fmt,
    load_rows,
    mean_of,
    per_start_effects,
    placebo_effects,
    pooled_cell,
    start_of,
    write_runs_csv,
    write_tables,
)
from rovergate.conditions import get_condition  # noqa: E402

if TYPE_CHECKING:
    from mission.study.spec import RunSpec, StudyConfig

#: Profiles whose pose drifts: where the pose-aware gate is compared with the frustum gate.
DRIFTING = ("drift", "drift+degraded")
#: Target of the issue: the pose-aware gate withholds at most this share of what the frustum
#: gate wrongly withholds under drift.
POSE_TARGET = 0.5
#: Target of the issue: pooled suppression precision of the ray-consistent gate.
PRECISION_TARGET = 0.9
#: Targets per gate, (precision, recall or None), pooled per platform: issue 16's for the ray
#: gate, issue 28's for the gate that reads beyond-range returns.
TARGETS: dict[str, tuple[float, float | None]] = {
    "gated-ray": (PRECISION_TARGET, None), "gated-ray-inf": (PRECISION_TARGET, 0.5)}


def suppression(rows: list[dict]) -> dict:
    """Pooled suppression figures of some runs of one withholding condition (ratios of sums),
    and the mean true surface wrongly withheld per step."""
    withheld = fp = predicted_fp = recalled = 0.0
    for r in rows:
        held, share = r.get("suppressed_per_step"), r.get("suppressed_fp_share")
        steps = r["steps"]
        if held is not None:
            withheld += held * steps
            if share is not None and math.isfinite(share):
                fp += held * share * steps
        # Recall counts the runs that record its denominator, and what they withheld: none
        # (no share: nothing withheld), or their share of it.
        known = share is not None and math.isfinite(share)
        if r.get("predicted_fp_per_step") is not None and held is not None \
                and (held == 0 or known):
            predicted_fp += r["predicted_fp_per_step"] * steps
            recalled += held * share * steps if held else 0.0
    return {"withheld": withheld, "withheld_fp": fp, "predicted_fp": predicted_fp,
            "recalled": recalled, "precision": fp / withheld if withheld else None,
            "recall": recalled / predicted_fp if predicted_fp else None,
            "wrongly_withheld_per_step": mean_of(r.get("wrongly_withheld_per_step")
                                               for r in rows)}


def _failures(rows: list[dict]) -> dict:
    clearance = [r["min_clearance_m"] for r in rows if r.get("min_clearance_m") is not None
                 and math.isfinite(r["min_clearance_m"])]
    gate = [r["gate_s"] for r in rows if r.get("gate_s") is not None]
    step = [r["median_step_s"] for r in rows if r.get("median_step_s") is not None]

    def total(k):
        v = [r.get(k) for r in rows]
        return int(sum(v)) if v and all(x is not None for x in v) else None
    return {"runs": len(rows), "collisions": total("collisions"),
            "collisions_planner_fault": total("collisions_planner_fault"),
            "collisions_unseen": total("collisions_unseen"),
            "stuck_steps": total("stuck_steps"),
            "stuck_runs": sum(1 for r in rows if (r.get("stuck_steps") or 0) > 0),
            "min_clearance_m_median": float(np.median(clearance)) if clearance else None,
            "fp_gain_share_mean": mean_of(r.get("fp_gain_share") for r in rows
                                        if r.get("fp_gain_share") is not None
                                        and math.isfinite(r["fp_gain_share"])),
            "gate_s_median": float(np.median(gate)) if gate else None,
            "gate_share_of_step": (float(np.median(gate)) / float(np.median(step))
                                   if gate and step and np.median(step) > 0 else None)}


def _reps(rows: list[dict]) -> dict:
    out: dict = {}
    for r in rows:
        out.setdefault((r["platform"], r["profile"], r["scene"], r["start"], r["condition"]),
                       set()).add(r["rep"])
    return out


def _s(v, digits=3, signed=False) -> str:
    return fmt(v, signed, digits) if v is not None else "—"


def _share(v, part, whole) -> str:
    """A pooled share with the point-steps it is of: a precision over a handful of points
    is no evidence of anything."""
    if v is None:  # nothing withheld (precision) or nothing to withhold (recall)
        return "—"
    return f"{v:.2f} ({_count(part)} / {_count(whole)})"


def cell_table(rows: list[dict], conditions: tuple[str, ...], resamples: int,
               key=start_of) -> tuple[list[str], dict]:
    """The rows of one platform and profile (or of all profiles of a platform, with ``key``
    including the profile): one line per condition and the placebo."""
    lines, figures = [], {}
    for c in conditions:
        runs = [r for r in rows if r["condition"] == c]
        if not runs:
            continue
        fig: dict = {}
        effect = per_start_effects(rows, c, "final_coverage", key=key)
        vs_gate = "—"
        if c == BASELINE:  # absolute
            text, fig["final_coverage"] = pooled_cell(list(effect.values()), False, 3, resamples)
        else:
            text, fig["delta_c_t"] = pooled_cell(list(effect.values()), True, 3, resamples)
            if c != FILTER and get_condition(c).withholds:
                g = per_start_effects(rows, c, "final_coverage", reference=FILTER, key=key)
                vs_gate, fig["delta_vs_gated"] = pooled_cell(list(g.values()), True, 3, resamples)
        sup = suppression(runs) if get_condition(c).withholds else {}
        fail = _failures(runs)
        fig.update(sup)
        fig.update(fail)
        figures[c] = fig
        lines.append(
            f"| {LABELS.get(c, c)} | {len(runs)} | {text} | {vs_gate} | "
            f"{_share(sup.get('precision'), sup.get('withheld_fp'), sup.get('withheld'))} | "
            f"{_share(sup.get('recall'), sup.get('recalled'), sup.get('predicted_fp'))} | "
            f"{_s(sup.get('wrongly_withheld_per_step'), 1)} | "
            f"{_s(fail['fp_gain_share_mean'], 3)} | "
            f"{fail['collisions_planner_fault']} / {fail['collisions_unseen']} | "
            f"{fail['stuck_steps']} ({fail['stuck_runs']}) | "
            f"{_s(fail['min_clearance_m_median'], 2)} | "
            f"{_s(fail['gate_s_median'], 4)} ({_s(fail['gate_share_of_step'], 3)}) |")
    p = placebo_effects(rows, "final_coverage", key)
    text, figures["placebo"] = pooled_cell([v for v in p.values() if v is not None], True, 3,
                                     resamples)
    lines.append(f"| Placebo (learned vs learned) | — | {text} | — | | | | | | | | |")
    return lines, figures


HEAD = ("| Condition | runs | C_T (learned) / ΔC_T vs learned [95% CI] | ΔC_T vs frustum gate "
        "[95% CI] | suppression precision | recall | true surface wrongly withheld / step | "
        "FP gain share | collisions: planner fault / unseen | stuck steps (runs) | "
        "min clearance, median (m) | gate s / step (share of step) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|")


def plot_coverage(rows: list[dict], cfg, out: Path) -> str:
    platforms, profiles = cfg.platform, cfg.profiles
    fig, axes = plt.subplots(len(platforms), len(profiles), squeeze=False,
                             figsize=(3.6 * len(profiles), 3.2 * len(platforms)), sharey=True)
    colours = dict(zip(cfg.conditions, plt.cm.tab10.colors, strict=False))
    for i, p in enumerate(platforms):
        for j, s in enumerate(profiles):
            ax = axes[i][j]
            for c in cfg.conditions:
                curves = [r["coverage"] for r in rows if (r["platform"], r["profile"],
                                                         r["condition"]) == (p, s, c)]
                if curves:
                    ax.plot(np.mean(curves, axis=0), color=colours[c], lw=1.6,
                            ls="--" if c == BASELINE else "-",
                            label=f"{c} ({len(curves)})")
            ax.set(title=f"{p}, {s}", ylim=(0, 1), xlabel="planning step")
            ax.grid(alpha=0.3)
            if j == 0:
                ax.set_ylabel("surface coverage (mean of runs)")
    axes[0][0].legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    name = "validation_coverage.png"
    fig.savefig(out / name, dpi=100)
    plt.close(fig)
    return name


def _count(n: float) -> str:
    return f"{n / 1e6:.1f}M" if n >= 1e6 else f"{n / 1e3:.0f}k" if n >= 1e4 else f"{n:.0f}"


def plot_suppression(figures: dict, cfg, out: Path) -> str:
    variants = [c for c in cfg.conditions if get_condition(c).withholds]
    fig, axes = plt.subplots(len(cfg.platform), 2, squeeze=False,
                             figsize=(11, 3.4 * len(cfg.platform)))
    width = 0.8 / max(len(variants), 1)
    x = np.arange(len(cfg.profiles))
    for i, p in enumerate(cfg.platform):
        for j, (key, title) in enumerate((("precision", "suppression precision"),
                                          ("recall", "suppression recall"))):
            ax = axes[i][j]
            for k, c in enumerate(variants):
                cells = [figures[p]["profiles"][s].get(c, {}) for s in cfg.profiles]
                v = [cell.get(key) for cell in cells]
                xs = x + (k - (len(variants) - 1) / 2) * width
                ax.bar(xs, [np.nan if y is None else y for y in v], width, label=c)
                for xi, yi, cell in zip(xs, v, cells, strict=True):
                    # How many points the share is of: a precision over a handful is no
                    # evidence of anything.
                    n = cell.get("predicted_fp" if key == "recall" else "withheld")
                    if n is not None and yi is not None:
                        ax.text(xi, min(yi, 0.93) + 0.02, _count(n), ha="center",
                                fontsize=6, rotation=90)
            if key == "precision":
                ax.axhline(PRECISION_TARGET, color="grey", ls=":", lw=1)
            ax.set(title=f"{p}: {title}", ylim=(0, 1.1), xticks=x,
                   xticklabels=cfg.profiles)
            ax.grid(alpha=0.3, axis="y")
    axes[0][0].legend(fontsize=7, loc="lower left")
    fig.suptitle("Pooled over runs (ratios of sums); on each bar, the point-steps the share "
                 "is of", fontsize=9)
    fig.tight_layout()
    name = "validation_suppression.png"
    fig.savefig(out / name, dpi=100)
    plt.close(fig)
    return name


def write_validation(cfg: StudyConfig, specs: list[RunSpec], out: Path) -> dict:
    """Every cell's tables in ``out/<platform>-<profile>/``; runs.csv, validation.md, the plots
    and summary.json of the whole study in ``out``."""
    sessions = json.loads((out / "study.json").read_text())["sessions"]
    rows: list[dict] = []
    cell_summaries = {}
    for p in cfg.platform:
        for s in cfg.profiles:
            cell = [x for x in specs if (x.platform, x.profile) == (p, s)]
            (out / f"{p}-{s}").mkdir(exist_ok=True)
            loaded = load_rows(cell, out / "runs")
            cell_summaries[f"{p}-{s}"] = write_tables(
                replace(cfg, platform=(p,)), cell, out / f"{p}-{s}", platform=p,
                sessions=sessions, loaded=loaded)
            rows += loaded[0]
    write_runs_csv(rows, out / "runs.csv")
    with_profile = lambda r: (r["profile"], r["scene"], r["start"])  # noqa: E731
    text = ["# The paper's required validation: gate variants under degraded sensing and drift",
            "", f"{cfg.steps} steps; scenes {', '.join(cfg.scenes)}; starts "
            f"{', '.join(cfg.starts)}; repetitions per condition and unit "
            f"{', '.join(str(n) for n in sorted({len(v) for v in _reps(rows).values()}))} "
            "(repetition r runs with seed r); "
            f"{len(rows)} of {len(specs)} runs finished. Sensing profiles: see "
            "`mission.study.runner.SENSING_PROFILES`.", ""]
    figures: dict = {}
    for p in cfg.platform:
        prow = [r for r in rows if r["platform"] == p]
        figures[p] = {"profiles": {}}
        for s in cfg.profiles:
            lines, figures[p]["profiles"][s] = cell_table(
                [r for r in prow if r["profile"] == s], cfg.conditions, cfg.bootstrap)
            text += [f"## {p}, {s}", "", *HEAD, *lines, ""]
        lines, figures[p]["pooled"] = cell_table(prow, cfg.conditions, cfg.bootstrap,
                                                 key=with_profile)
        text += [f"## {p}, pooled over the {len(cfg.profiles)} profiles "
                 "(unit: profile, scene, start)", "", *HEAD, *lines, ""]
        drift = [r for r in prow if r["profile"] in DRIFTING]
        w = {c: suppression([r for r in drift if r["condition"] == c])
             ["wrongly_withheld_per_step"] for c in ("gated", "gated-pose")}
        ratio = (w["gated-pose"] / w["gated"] if w["gated"] and w["gated-pose"] is not None
                 else None)
        figures[p]["drift_wrongly_withheld"] = {**w, "ratio": ratio}
    everything = {c: suppression([r for r in rows if r["condition"] == c])
                  for c in cfg.conditions if get_condition(c).withholds}
    figures["pooled_suppression"] = everything
    text += ["## Targets", ""]
    # Suppression per gate and platform, with the point-steps behind each share (issue 16's
    # target for the ray gate, precision >= 0.9; issue 28's for gated-ray-inf, precision
    # >= 0.9 with recall >= 0.5, on both platforms).
    for c in everything:
        for p in cfg.platform:
            sup = suppression([r for r in rows if r["condition"] == c and r["platform"] == p])
            figures[p].setdefault("suppression", {})[c] = sup
            target = TARGETS.get(c)
            met = (None if target is None or sup["precision"] is None
                   else sup["precision"] >= target[0]
                   and (target[1] is None or (sup["recall"] or 0) >= target[1]))
            text.append(
                f"- {p}, {LABELS.get(c, c)}: suppression precision "
                f"{_share(sup['precision'], sup['withheld_fp'], sup['withheld'])} point-steps, "
                f"recall {_share(sup['recall'], sup['recalled'], sup['predicted_fp'])}"
                + ("" if target is None else
                   f" (target precision ≥ {target[0]}"
                   + (f" with recall ≥ {target[1]}" if target[1] is not None else "")
                   + f": {'met' if met else 'not met'})") + ".")
    for p in cfg.platform:
        d = figures[p]["drift_wrongly_withheld"]
        text.append(f"- {p}, under drift ({' and '.join(DRIFTING)}): true surface wrongly "
                    f"withheld per step, frustum gate {_s(d['gated'], 1)}, pose-aware gate "
                    f"{_s(d['gated-pose'], 1)}: ratio {_s(d['ratio'], 2)} (target ≤ "
                    f"{POSE_TARGET}).")
        for c, fig in figures[p]["pooled"].items():
            if c in (BASELINE, "placebo") or "delta_c_t" not in fig:
                continue
            ci = fig["delta_c_t"]["ci95"]
            if not ci:  # no learned run to pair with
                text.append(f"- {p}, {c}: no learned runs to pair with.")
                continue
            vg = fig.get("delta_vs_gated", {}).get("ci95")
            # A bootstrap over one unit is that unit's value: at least two units to count.
            meets = (fig["delta_c_t"]["n"] >= 2 and ci[0] > 0
                     and (c == FILTER or (vg and vg[0] > 0))
                     and fig["collisions_planner_fault"] == 0)
            text.append(f"- {p}, {c}: pooled ΔC_T vs learned CI {_s(ci[0], 3, True)} to "
                        f"{_s(ci[1], 3, True)}" + (f", vs frustum gate {_s(vg[0], 3, True)} "
                                                   f"to {_s(vg[1], 3, True)}" if vg else "")
                        + f", planner-fault collisions {fig['collisions_planner_fault']}: "
                        + ("meets" if meets else "does not meet")
                        + " the coverage target.")
    text += ["", "Columns: C_T is absolute for `learned`; ΔC_T pairs run r with the learned "
             "(or frustum-gate) run r of the same scene, start, platform and profile, averaged "
             "over repetitions per unit, then over units, with a bootstrap 95% CI resampling "
             f"units ({cfg.bootstrap} resamples). Suppression precision: of the points a gate "
             "withheld, the share farther than 0.03 d_scene from the true surface; recall: "
             "of the prediction's oracle false positives, the share withheld; both pooled as "
             "ratios of sums over runs. True surface wrongly withheld: withheld points within "
             "0.03 d_scene of the true surface, per step, mean over runs. FP gain share: the "
             "share of the chosen viewpoint's rendered gain owed to oracle false positives. "
             "Collisions: totals over runs, planner fault (the map held an obstacle within "
             "the planner's margin of the contact) / unseen geometry. Stuck steps: steps with "
             "under 0.5 m of net progress over the last 10, total (runs with any). Gate s / "
             "step: median over runs of each run's median gate stage, and its share of the "
             "median step. Every figure but coverage is evaluation only: no module sees truth."]
    (out / "validation.md").write_text("\n".join(text) + "\n")
    plots = [plot_coverage(rows, cfg, out), plot_suppression(figures, cfg, out)]
    summary = {
        "runs": len(rows), "expected_runs": len(specs),
        "wall_s": sum(s["wall_s"] for s in sessions), "sessions": sessions,
        "run_wall_s_median": float(np.median([r["wall_s"] for r in rows])) if rows else None,
        "validation": figures, "plots": plots,
        "cells": {k: {"table1": v["table1"], "failure_modes": v["failure_modes"]}
                  for k, v in cell_summaries.items()},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float) + "\n")
    return summary
