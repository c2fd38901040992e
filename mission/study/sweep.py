"""The sweep of a gate's evidence count K and support radius epsilon (``python -m
mission.study.sweep``), and the choice of its default.

Every setting is a study of its own (``OUT/k<K>-eps<E>/``, resumable like any study): the gate
condition on the sweep's starts, with `learned` as every study runs it. The references, which
read no gate setting, are one more study (``OUT/references/``): `learned-fp` (the oracle's
removal of every false positive), `learned+fn` and `truth`. `learned` does not read K or epsilon
either, so its runs must be the same in every setting's study, to the last digit: the sweep
checks it (a determinism check for free) and says so.

Per setting, pooled over its runs as ratios of sums (:func:`mission.study.validation.suppression`):
suppression precision (true false positives withheld / withheld) and recall (/ false positives
predicted), true surface wrongly withheld per step, and coverage against `learned` (paired by
start, bootstrap 95% CI over starts). The choice, declared before the numbers: the setting of
largest recall among those with precision at least ``--precision``; if none reaches it, the one
of largest precision (and the sweep says that the target was missed). Its figures on starts the
sweep did not use come from the validation study (docs/validation.md).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mission.study import tables as T
from mission.study.spec import StudyConfig
from rovergate.config import MissionConfig

log = logging.getLogger("rovergate.sweep")


@dataclass
class SweepConfig:
    """The sweep's settings."""

    condition: str = "gated-ray-inf"
    """The gate condition swept."""
    k: tuple[int, ...] = (1, 2, 3)
    """Evidence counts K (--gate.k)."""
    epsilon_frac: tuple[float, ...] = (0.015, 0.03, 0.06)
    """Support radii epsilon as fractions of d_scene (--gate.epsilon-frac)."""
    starts: tuple[str, ...] = ("b", "c")
    """The sweep's starts (of every scene); the others stay out of it."""
    platform: str = "flyer"
    """The platform."""
    steps: int = 100
    """Planning steps per run."""
    seeds: str = "0"
    """Seeds of every run (A..B or a list)."""
    precision: float = 0.9
    """The precision the chosen setting must reach."""
    workers: int = 0
    """Worker processes (0: one per core)."""
    out: Path = Path("runs/gate-sweep")
    """Directory of the sweep."""
    references: bool = True
    """Run the reference study (learned-fp, learned+fn, truth) too."""
    bootstrap: int = 10_000
    """Bootstrap resamples."""
    mission: MissionConfig = field(default_factory=MissionConfig)
    """Every other mission setting."""


def _name(k: int, eps: float) -> str:
    return f"k{k}-eps{eps:g}"


def _study(cfg: SweepConfig, conditions: tuple[str, ...], out: Path,
           k: int | None = None, eps: float | None = None) -> StudyConfig:
    mission = cfg.mission
    if k is not None:
        # The swept gate's own fields, and the shared ones (which the sweep committed on
        # 2026-12-05 set: gated-ray-inf read them then).
        fields = {"k": k, "epsilon_frac": eps}
        if cfg.condition == "gated-ray-inf":
            fields.update(ray_inf_k=k, ray_inf_epsilon_frac=eps)
        mission = replace(mission, gate=replace(mission.gate, **fields))
    return StudyConfig(starts=cfg.starts, conditions=conditions, platform=(cfg.platform,),
                       steps=cfg.steps, seeds=cfg.seeds, workers=cfg.workers, out=out,
                       bootstrap=cfg.bootstrap, progress=False, mission=mission)


def settings(cfg: SweepConfig) -> list[tuple[int, float]]:
    return [(k, e) for k in cfg.k for e in cfg.epsilon_frac]


def run(cfg: SweepConfig) -> int:
    from mission.study.runner import main as study
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    plan = [(_name(k, e), _study(cfg, (cfg.condition,), out / _name(k, e), k, e))
            for k, e in settings(cfg)]
    if cfg.references:
        plan.append(("references", _study(cfg, ("learned-fp", "learned+fn", "truth"),
                                          out / "references")))
    for name, study_cfg in plan:
        log.info("sweep: %s", name)
        if code := study(study_cfg):
            return code
    write_sweep(cfg)
    return 0


def _rows(out: Path) -> list[dict]:
    return T.rows_from_csv(out)[0]


def write_sweep(cfg: SweepConfig) -> dict:
    """OUT/sweep.md and OUT/sweep.json from the finished studies."""
    from mission.study.validation import suppression
    out = Path(cfg.out)
    figures: dict = {"condition": cfg.condition, "starts": list(cfg.starts),
                     "platform": cfg.platform, "seeds": cfg.seeds, "settings": {}}
    learned_ref = None
    same_learned = True
    lines = ["| K | epsilon (x d_scene) | withheld | precision | recall | true surface wrongly "
             "withheld / step | ΔC_T vs learned [95% CI] | collisions | stuck steps |",
             "|---|---|---|---|---|---|---|---|---|"]
    for k, e in settings(cfg):
        rows = _rows(out / _name(k, e))
        learned = sorted((r["scene"], r["start"], r["rep"], r["final_coverage"])
                         for r in rows if r["condition"] == T.BASELINE)
        learned_ref = learned_ref or learned
        same_learned &= learned == learned_ref
        gate = [r for r in rows if r["condition"] == cfg.condition]
        sup = suppression(gate)
        effect = T.per_start_effects(rows, cfg.condition, "final_coverage")
        text, fig = T.pooled_over(effect, sorted(effect), True, 3, cfg.bootstrap)
        fig.update(sup, collisions=int(sum(r["collisions"] for r in gate)),
                   stuck_steps=int(sum(r.get("stuck_steps") or 0 for r in gate)),
                   runs=len(gate))
        figures["settings"][_name(k, e)] = {"k": k, "epsilon_frac": e, **fig}
        lines.append(f"| {k} | {e:g} | {sup['withheld']:,.0f} | {T.fmt(sup['precision'], False, 3)}"
                     f" | {T.fmt(sup['recall'], False, 3)} | "
                     f"{T.fmt(sup['wrongly_withheld_per_step'], False, 0)} | {text} | "
                     f"{fig['collisions']} | {fig['stuck_steps']} |")
    chosen, met = choose(figures["settings"], cfg.precision)
    figures["chosen"], figures["target_met"] = chosen, met
    figures["learned_identical_across_settings"] = same_learned
    refs = []
    if (out / "references" / "runs.csv").exists():
        rows = _rows(out / "references")
        figures["references"] = {}
        refs = ["", "References on the same starts and seeds (ΔC_T against `learned`, "
                "bootstrap 95% CI over starts):", ""]
        for c in ("learned-fp", "learned+fn", "truth"):
            effect = T.per_start_effects(rows, c, "final_coverage")
            text, fig = T.pooled_over(effect, sorted(effect), True, 3, cfg.bootstrap)
            figures["references"][c] = fig
            refs.append(f"- {T.LABELS.get(c, c)}: {text}")
    c = figures["settings"][chosen]
    head = [f"# Sweep of `{cfg.condition}`: K and epsilon", "",
            f"Platform {cfg.platform}, starts {', '.join(cfg.starts)} of every scene, seeds "
            f"{cfg.seeds}, {cfg.steps} steps; {len(settings(cfg))} settings "
            "(`python -m mission.study.sweep`, mission/study/sweep.py). Suppression pooled as "
            "ratios of sums over every run and step of the setting.", "", *lines, *refs, "",
            f"**Chosen** (the rule, declared before the numbers: the largest recall at "
            f"precision >= {cfg.precision:g}, else the largest precision): K = {c['k']}, "
            f"epsilon = {c['epsilon_frac']:g} d_scene, precision "
            f"{T.fmt(c['precision'], False, 3)}, recall {T.fmt(c['recall'], False, 3)}"
            + ("." if met else f": **no setting reached precision {cfg.precision:g}**."),
            "",
            "`learned` reads neither K nor epsilon: its runs are "
            + ("the same, to the last digit, in every setting's study."
               if same_learned else "NOT the same in every setting's study (a determinism "
               "failure: report it)."), ""]
    (out / "sweep.md").write_text("\n".join(head))
    (out / "sweep.json").write_text(json.dumps(figures, indent=1) + "\n")
    return figures


def choose(settings_figures: dict, precision: float) -> tuple[str, bool]:
    """The chosen setting's name, and whether it met the precision (module docstring)."""
    def val(v):
        return -np.inf if v is None else v
    ok = [n for n, f in settings_figures.items() if val(f["precision"]) >= precision]
    if ok:
        return max(ok, key=lambda n: (val(settings_figures[n]["recall"]), n)), True
    return max(settings_figures, key=lambda n: (val(settings_figures[n]["precision"]),
                                                val(settings_figures[n]["recall"]))), False


if __name__ == "__main__":
    import tyro

    from rovergate.logs import init_logging
    init_logging("sweep")
    raise SystemExit(run(tyro.cli(SweepConfig)))
