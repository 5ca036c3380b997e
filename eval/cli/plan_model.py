"""The model a plan is made on, and the survey that lets the model take in the band first.

`plan_on_model` plans the band on the adaptive model as the filter sees it now (the
planning.field_model.FieldModel of the field the filter bounds the shaft with, so that the
plan keeps to the filter's own rule). `survey_band` sweeps the band deeper than the
shaving, filter on, through the closed loop against the true eye, one or more times: each
pass is planned on the model the previous one left, so that a pass reaches band the model
could not place before it (on the pointed eye the first pass's sphere leaves a quarter of
the band to the shaft; the second pass's, refitted on what the first measured, reaches
nearly all of it). Units: mm, s.
"""
from __future__ import annotations

import dataclasses
import math
import re
import shutil
from pathlib import Path

import numpy as np

from eval.cli.io import UsageError
from eval.cli.progress import phase

# planning.peripheral.BandSpec's parameters (named in its messages) -> the flags that set them
FLAG_OF_PARAMETER = {"spacing_mm": "--sweep-mm", "standoff_mm": "--standoff-mm", "tip_speed_mm_s": "--tip-speed-mm-s",
                     "band z_E range": "--band", "z_min": "z0", "z_max": "z1", "z_min_E": "z0", "z_max_E": "z1",
                     "trust_angle_deg": "--trust-angle-deg", "port_max_deg": "--port-angle-deg"}
_PARAMETER = re.compile(r"\b(" + "|".join(sorted(map(re.escape, FLAG_OF_PARAMETER), key=len, reverse=True)) + r")\b")


def flags_named(message: str) -> str:
    """`message` with planning's parameter names replaced by the flags that set them."""
    return _PARAMETER.sub(lambda m: FLAG_OF_PARAMETER[m.group(1)], message)


SHAVE_ROOM_MM = 0.2  # between the filter's boundary and the shaving standoff: the filter need not step in


def check_standoff(standoff_mm: float, boundary_mm: float, what: str) -> None:
    """UsageError naming --standoff-mm when it lies less than SHAVE_ROOM_MM beyond the
    boundary `boundary_mm` (mm; `what`: the boundary's description)."""
    if standoff_mm < boundary_mm + SHAVE_ROOM_MM:
        raise UsageError(f"--standoff-mm {standoff_mm:g} is below {what} ({boundary_mm:.3f} mm) + {SHAVE_ROOM_MM:g} mm "
                         f"to shave without the filter stepping in; use at least "
                         f"{math.ceil((boundary_mm + SHAVE_ROOM_MM) * 100.0) / 100.0:.2f} mm")


def plan_on_model(args, loop, build, scenario, visit, spec):
    """(the filter's snapshot of the model, the planning.field_model.FieldModel of the field it
    bounds the shaft with, `spec` with its boundary (d_safe + calibration), the least boundary
    over the band's targets (mm), the planning.multiport plan) on the model `build.model`
    as it is now; UsageError when the filter does not trust it, the standoff lies below its
    boundary, or no cell can be swept."""
    from eval.closed_loop import semi_axes_mm
    from planning.field_model import FieldModel, least_uncertainty_mm
    from planning.ik import IKFailure
    from planning.multiport import plan_ports
    from planning.peripheral import band_surface

    trusted = loop.model.snapshot_for(build.model, build.coverage, 0.0)
    if (trusted.field if loop.config.local_model else trusted.shape) is None:
        radii = semi_axes_mm(build.model.shape)
        raise UsageError(f"cannot plan: the filter does not trust this {build.kind_final} model (semi-axes "
                         f"{', '.join(f'{r:.1f}' for r in radii)} mm; an eye's lie in {loop.config.model_radius_range_mm} "
                         f"mm) and would hold the instrument inside the conservative prior, away from the band")
    # what the filter will bound the shaft with (the sphere if the ellipsoid is no eye's), as one rule: h - k u;
    # the local model's surface is its field's, its bound the barrier's (planning.field_model.FieldModel)
    shaft = loop.filter.field_objects(trusted)[1]
    model = FieldModel(trusted.field if loop.config.local_model else shaft, loop.config.filter.sigma_factor, trusted.kind,
                       bound=shaft)
    try:
        spec = dataclasses.replace(spec, boundary_mm=loop.config.filter.boundary_mm(0.0))  # d_safe + calibration
    except ValueError as exc:
        raise UsageError(flags_named(str(exc))) from None
    try:
        surface = band_surface(model, scenario.eye_pose, spec)
    except ValueError as exc:  # the band leaves this model
        raise UsageError(f"cannot plan: {flags_named(str(exc))}") from None
    boundary = spec.boundary_mm + least_uncertainty_mm(model, surface, spec.standoff_mm)
    check_standoff(spec.standoff_mm, boundary, f"the boundary the filter keeps from this {trusted.kind} model")
    try:
        with phase(f"planning the band {spec.standoff_mm:g} mm deep through {len(visit)} ports (reachability, "
                   f"assignment, sweeps, switches)"):
            plan = plan_ports(loop.robot, scenario, model, visit, spec, surface)
    except (ValueError, IKFailure) as exc:
        raise UsageError(f"cannot plan: {flags_named(str(exc))}") from None
    return trusted, model, spec, boundary, plan


def survey_band(args, loop, build, scenario, visit, spec, log_dir: Path) -> dict:
    """Sweep the band `args.survey_mm` deeper than `spec` `args.survey_passes` times, each
    pass planned on the model as the previous one left it (plan_on_model) and executed
    through the loop, the model taking in what the fibre measures; each pass logged to
    log_dir/survey_<k>.mcap. Returns plan.json's `survey`: its depth (`standoff_mm`), per
    pass its planned cells, band coverage, true clearance, interventions and durations
    (`passes`), and over all passes `band_coverage` (the cells of the band of the last
    pass's model that any pass swept), `planned_cells` (the last pass's planned cells),
    `planned_cells_swept` (the least, over the passes, of a pass's fraction of its own
    planned cells swept), `filter_intervention_fraction`, `steps`, `intervened_steps`,
    `min_true_clearance_mm`, `violations`, `failsafe_stops`, `duration_s`. UsageError as
    plan_on_model."""
    from eval.experiments.plan_execution import execution_figures, executed_passes, swept_cells
    from eval.log.writer import RunLogger

    deeper = dataclasses.replace(spec, standoff_mm=spec.standoff_mm + args.survey_mm)
    passes, ports_W = [], []
    for k in range(1, args.survey_passes + 1):
        trusted, _, survey_spec, _, plan = plan_on_model(args, loop, build, scenario, visit, deeper)
        executed = executed_passes(loop.robot, plan)
        with phase(f"survey pass {k} of {args.survey_passes}: the band {deeper.standoff_mm:g} mm deep "
                   f"({len(executed)} passes through the closed loop, the model taking in what the fibre measures): "
                   f"{sum(p.duration_s for p in executed):.0f} simulated s"):
            with RunLogger(log_dir / f"survey_{k}.mcap", loop.config.filter,
                           metadata={"shape": args.shape, "run": f"survey pass {k}"}) as log:
                run = loop.run_segments([p.segment() for p in executed], model=build.model, coverage=build.coverage,
                                        logger=log)
        figures = execution_figures(loop.robot, run, executed, plan, survey_spec.spacing_mm, loop.config.filter.d_safe_mm,
                                    loop.scenario.eye)
        ports_W.append(figures.sweep_ports_W)
        passes.append({"model_kind": trusted.kind, "planned_cells": int((plan.port_of >= 0).sum()),
                       "plan_time_s": plan.plan_time_s, "duration_s": float(run.duration_s), "steps": int(len(run.t)),
                       "intervened_steps": int(np.sum(run.intervened)), **figures.figures})
    steps = sum(p["steps"] for p in passes)
    swept = swept_cells(plan.band, np.vstack(ports_W), survey_spec.spacing_mm)  # the last model's band, by any pass
    return {"standoff_mm": deeper.standoff_mm, "passes": passes, "band_coverage": float(swept.mean()),
            "planned_cells": passes[-1]["planned_cells"],
            "planned_cells_swept": min(p["planned_cells_swept"] for p in passes),
            "steps": steps, "intervened_steps": sum(p["intervened_steps"] for p in passes),
            "filter_intervention_fraction": sum(p["intervened_steps"] for p in passes) / steps,
            "min_true_clearance_mm": min(p["min_true_clearance_mm"] for p in passes),
            "violations": sum(p["violations"] for p in passes),
            "failsafe_stops": sum(p["failsafe_stops"] for p in passes),
            "duration_s": sum(p["duration_s"] for p in passes)}


def move_logs(src: Path, out: Path) -> list[Path]:
    """Move the survey's logs from `src` into `out` (made by then): they are written there only
    once the plan has been made."""
    moved = []
    for f in sorted(src.glob("survey_*.mcap")):
        moved.append(Path(shutil.move(str(f), out / f.name)))
    return moved
