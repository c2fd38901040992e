"""A held-out test of the paper's targeted claim (``rovergate study --select-from DIR --seeds
3..12``).

The paper's Table 2 reports the filter on "targeted failure-prone starts selected by the
diagnosis", and the study's own Table 2 selects them the same way: the starts where the learned
baseline fails most. Selected and measured on the same runs, the effect is inflated by
regression to the mean (a start picked for a bad learned run looks better next time under any
condition, the placebo's halves included). This design separates the two:

1. **Select** the starts from a finished study (``--select-from DIR``, its ``runs.csv``) by the
   rule of :func:`mission.study.tables.paper_selection` (the 6 lowest mean learned C_T, and the
   6 largest mean truth − learned gap) and its Low and High strata (:func:`tables.strata`),
   and **declare** the selection in ``OUT/selection.json`` before any run starts. A resumed
   study recomputes it and refuses to go on if it differs.
2. **Measure** on seeds that study never ran (``--seeds``, refused if one overlaps): every
   condition on the union of the two selections, each seed paired across conditions.
3. **Report** (``OUT/heldout.md``, and ``heldout`` in ``summary.json``): per start, the paired
   effect with an exact sign-flip p-value and Holm's correction across the starts; per group
   (each selection, their union, the Low stratum), the pooled effect with a bootstrap interval
   over starts and a sign-flip p-value over starts, beside the same starts' in-sample effect
   in the source study (the selected figure) and beside the placebo on the new seeds (learned
   against learned, odd seeds against even ones).

The High stratum's starts are not run unless a selection holds them: its held-out effect comes
from cross-fitting inside a study (:func:`mission.study.tables.crossfit_strata`), where each
repetition's stratum is chosen from the other repetitions.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from mission.study import tables as T
from mission.study.spec import StudyConfig, parse_seeds
from rovergate.errors import ConfigError

SELECTION_FILE = "selection.json"
#: The rule, as the declaration records it.
RULE = (f"paper_selection: the {T.SELECTION_SIZE} starts of lowest mean learned C_T (a) and "
        f"the {T.SELECTION_SIZE} of largest mean paired truth − learned C_T (b) over the "
        f"source's repetitions; strata Low (mean learned C_T < {T.LOW}) and High (> {T.HIGH})")


def source_rows(select_from: str | Path) -> list[dict]:
    """The runs of a finished study (its runs.csv), with the fields the selection reads."""
    path = Path(select_from) / "runs.csv"
    if not path.is_file():
        raise ConfigError(f"--select-from {select_from}: no runs.csv there; give the directory "
                          "of a finished study (e.g. docs/results)")
    rows = []
    with open(path, newline="") as f:
        for i, r in enumerate(csv.DictReader(f), start=2):
            try:
                rows.append({"scene": r["scene"], "start": r["start"],
                             "condition": r["condition"], "rep": int(r["rep"]),
                             "seed": int(r["seed"]),
                             "final_coverage": float(r["final_coverage"])})
            except (KeyError, ValueError) as e:
                raise ConfigError(f"--select-from {path} line {i}: not a study's row ({e}); "
                                  "give the directory of a finished study") from None
    if not any(r["condition"] == T.BASELINE for r in rows):
        raise ConfigError(f"--select-from {path}: no `{T.BASELINE}` runs to select from")
    return rows


def _names(keys) -> list[str]:
    return [T.start_name(k) for k in keys]


def _keys(names) -> list[T.Start]:
    return [tuple(n.split("/", 1)) for n in names]  # type: ignore[misc]


def choose(select_from: str | Path) -> dict:
    """The declaration: the source, its seeds, the rule and the starts it chose."""
    rows = source_rows(select_from)
    groups = T.strata(rows)
    sel = T.paper_selection(rows, groups["All"])
    a, b = sel["lowest_learned"], sel["largest_truth_gap"] or []
    union = list(dict.fromkeys([*a, *b]))
    return {"source": str(select_from), "rule": RULE,
            "source_seeds": sorted({r["seed"] for r in rows}),
            "source_runs": len(rows),
            "lowest_learned": _names(a), "largest_truth_gap": _names(b) if b else None,
            "low": _names(groups["Low"]), "high": _names(groups["High"]),
            "starts": _names(union)}


def check(cfg: StudyConfig) -> list[T.Start]:
    """A held-out study's checks before any run: seeds the source never ran, a selection
    inside --scenes and --starts. Returns the selected (scene, start) pairs: the union of the
    two selections."""
    decl = choose(cfg.select_from)
    used = set(decl["source_seeds"])
    if overlap := sorted(used & set(parse_seeds(cfg.seeds))):
        raise ConfigError(f"--seeds: {', '.join(map(str, overlap))} were run by the study at "
                          f"--select-from (its seeds are {', '.join(map(str, sorted(used)))}); "
                          "a held-out test needs seeds it never ran, e.g. --seeds "
                          f"{max(used) + 1}..{max(used) + 10}")
    chosen = _keys(decl["starts"])
    if missing := [f"{a}/{b}" for a, b in chosen
                   if a not in cfg.scenes or b not in cfg.starts]:
        raise ConfigError(f"--select-from chose {', '.join(missing)}, outside --scenes and "
                          "--starts; leave those flags at their defaults")
    return chosen


def declare(select_from: str | Path, out: Path, seeds: tuple[int, ...]) -> dict:
    """Write ``out/selection.json`` (once, before any run), or check the one there."""
    decl = {**choose(select_from), "seeds": list(seeds)}
    path = out / SELECTION_FILE
    if path.exists():
        saved = json.loads(path.read_text())
        saved.pop("declared", None)
        if saved != decl:
            raise ConfigError(f"{path} declares another selection than {select_from} gives "
                              "now (the source changed, or other --seeds); give --out a new "
                              "directory")
        return decl
    import time
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps({"declared": time.strftime("%Y-%m-%d %H:%M:%S"), **decl},
                              indent=1) + "\n")
    tmp.replace(path)
    return decl


# ----------------------------------------------------------------------------- the report

def _pooled_p(effects: list[float]) -> float:
    """Exact sign-flip p over starts of their mean effects (the start is the unit)."""
    return T.signflip_p(effects) if effects else float("nan")


def heldout_table(rows: list[dict], decl: dict, conditions: tuple[str, ...], resamples: int
                  ) -> tuple[str, dict]:
    """heldout.md's tables from the new runs (``rows``) and the declaration."""
    source = source_rows(decl["source"])
    others = [c for c in conditions if c != T.BASELINE]
    starts = _keys(decl["starts"])
    figures: dict = {"selection": {k: decl[k] for k in ("lowest_learned", "largest_truth_gap",
                                                         "low", "starts")},
                     "seeds": decl["seeds"], "conditions": {}}
    lines = []
    placebo_new = T.placebo_effects(rows, "final_coverage")
    groups = [("Selection (a): lowest learned C_T", decl["lowest_learned"]),
              ("Selection (b): largest truth − learned gap", decl["largest_truth_gap"]),
              ("Both selections", decl["starts"]),
              (f"Low stratum (source learned C_T < {T.LOW})",
               [n for n in decl["low"] if n in decl["starts"]])]
    for c in others:
        deltas = T.paired_deltas(rows, c, "final_coverage")
        keys = [k for k in starts if k in deltas]
        if not keys:
            continue
        effect = {k: float(np.mean(list(deltas[k].values()))) for k in keys}
        p = [T.signflip_p(list(deltas[k].values())) for k in keys]
        p_holm = T.holm(p)
        in_sample = T.per_start_effects(source, c, "final_coverage")
        label = T.LABELS.get(c, c)
        lines += [f"## {label} − learned, per start", "",
                  "| Start | chosen by | learned C_T, source → new seeds | Δ held out (new "
                  "seeds) | seeds | p | p (Holm) | Δ in sample (source) |",
                  "|---|---|---|---|---|---|---|---|"]
        fig_c: dict = {"starts": {}, "groups": {}}
        learned = T.per_start_effects(rows, T.BASELINE, "final_coverage")
        learned_src = T.per_start_effects(source, T.BASELINE, "final_coverage")
        for i, k in enumerate(keys):
            name = T.start_name(k)
            by = "+".join(x for x, g in (("a", decl["lowest_learned"]),
                                          ("b", decl["largest_truth_gap"] or []),
                                          ("Low", decl["low"])) if name in g)
            mark = " *" if p_holm[i] < T.ALPHA else ""
            lines.append(f"| {name} | {by} | {T.fmt(learned_src.get(k), False, 3)} → "
                         f"{T.fmt(learned.get(k), False, 3)} | "
                         f"{T.fmt(effect[k], True, 3)} | {len(deltas[k])} | "
                         f"{T.fmt_p(p[i])} | {T.fmt_p(p_holm[i])}{mark} | "
                         f"{T.fmt(in_sample.get(k), True, 3)} |")
            fig_c["starts"][name] = {"delta": effect[k], "values": list(deltas[k].values()),
                                     "p_signflip": p[i], "p_holm": float(p_holm[i]),
                                     "in_sample": in_sample.get(k),
                                     "learned_source": learned_src.get(k),
                                     "learned_new": learned.get(k)}
        lines += ["", f"## {label} − learned, pooled over starts", "",
                  "| Starts | n | Δ held out [95% CI] | p over starts | placebo, new seeds "
                  "[95% CI] | Δ in sample (source) [95% CI] |", "|---|---|---|---|---|---|"]
        for glabel, names in groups:
            if not names:
                continue
            gk = [k for k in _keys(names) if k in effect]
            text, fig = T.pooled_over(effect, gk, True, 3, resamples)
            ptext, fig["placebo"] = T.pooled_over(placebo_new, gk, True, 3, resamples)
            itext, fig["in_sample"] = T.pooled_over(in_sample, _keys(names), True, 3, resamples)
            fig["p_over_starts"] = _pooled_p([effect[k] for k in gk])
            fig_c["groups"][glabel] = fig
            lines.append(f"| **{glabel}** | {len(gk)} | {text} | "
                         f"{T.fmt_p(fig['p_over_starts'])} | {ptext} | {itext} |")
        lines.append("")
        figures["conditions"][c] = fig_c
    seeds = decl["seeds"]
    notes = [
        f"Selected from `{decl['source']}` (seeds {', '.join(map(str, decl['source_seeds']))}) "
        f"by {decl['rule']}; declared in `selection.json` before any run. Measured on seeds "
        f"{seeds[0]}..{seeds[-1]} ({len(seeds)} seeds), which the source never ran. Δ: per "
        "start, the mean over seeds of the paired change (condition − learned, same seed), "
        "then pooled as the mean over starts; brackets: bootstrap 95% CI resampling starts "
        f"({resamples} resamples). p: exact two-sided sign-flip test of a start's paired "
        "changes over its seeds, Holm-adjusted over the starts of the table (* below "
        f"{T.ALPHA}); p over starts: the same test on the starts' mean changes. Placebo: the "
        "new seeds' learned runs against each other (odd positions against even ones), the "
        "noise floor of a held-out Δ. Δ in sample: the same starts in the source, where they "
        "were selected, i.e. the figure the selection inflates. Learned C_T, source → new "
        "seeds: a start chosen for its failures fails less on new seeds (regression to the "
        "mean), under every condition.",
    ]
    return "\n".join(["# Held-out test of the targeted claim", "", *notes, "", *lines]), \
        figures


def write_heldout(cfg, specs, out: Path, decl: dict, summary: dict,
                  rows: list[dict] | None = None) -> dict:
    """OUT/heldout.md, and ``heldout`` in OUT/summary.json (from ``rows``, or the runs)."""
    if rows is None:
        rows, _ = T.load_rows(specs, out / "runs")
    text, figures = heldout_table(rows, decl, cfg.conditions, cfg.bootstrap)
    (out / "heldout.md").write_text(text)
    summary = {**summary, "heldout": figures}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
