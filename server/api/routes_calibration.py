"""Calibration: fit Us and K to a case table, and apply them to a session's material."""

from __future__ import annotations

from fastapi import APIRouter

from ..calib.design import ModelSetup, Sensitivities
from ..calib.fit import FitError, FitOptions, calibrate, finite_or_none, summary_of
from ..calib.table import CaseRow, CaseTableError, row_from_mapping
from ..model.params import THESIS_K
from .deps import PlaneDep, SessionPath
from .errors import Invalid
from .models import CalibrationApply, FitRequest

router = APIRouter(tags=["calibration"])


def run_fit(body: FitRequest, default_k: float = THESIS_K) -> dict:
    """The fit as ``burrforce calibrate --json`` prints it (422 on data that cannot be fitted).
    """
    try:
        rows: list[CaseRow] = [row_from_mapping(r.model_dump(), f"cases[{i}]")
                               for i, r in enumerate(body.cases)]
        options = FitOptions(fit_k=body.fit == "us,k",
                             k=body.k if body.k is not None else default_k,
                             components=tuple(body.components), confidence=body.confidence,
                             intervals=body.intervals)
        cal = calibrate(rows, options, Sensitivities(ModelSetup(spin=body.spin)))
        return finite_or_none(cal.as_dict())  # type: ignore[return-value]
    except (FitError, CaseTableError, ValueError) as exc:
        raise Invalid(str(exc)) from None


@router.post("/calibration/fit")
def fit(body: FitRequest) -> dict:
    """Fit Us (and K) to a case table: estimates with confidence intervals, residuals per
    component and case, the thesis's cross-validation (fit parallel + perpendicular, predict
    diagonal) and leave-one-case-out. Applies nothing."""
    return run_fit(body)


@router.post("/sessions/{session_id}/calibration")
def apply_calibration(body: CalibrationApply, plane: PlaneDep,
                      session_id: int = SessionPath) -> dict:
    """Set a session material's Us and K from a calibration: fit ``fit.cases`` here, or take
    ``us_n_mm2`` (and ``k``) fitted elsewhere. Applied between two packets, like a material
    PATCH; the material's previous values and the fit's summary are kept (GET)."""
    if (body.fit is None) == (body.us_n_mm2 is None):
        raise Invalid("give either fit (a case table to fit here) or us_n_mm2 (a value "
                      "fitted elsewhere), not both or neither")
    if body.fit is not None and body.k is not None:
        raise Invalid("k goes inside fit (held fixed when fit.fit = 'us'); with a fit, "
                      "the applied K is the fit's")
    label, material = plane.calibration_target(session_id, body.label)
    if body.fit is None:
        return plane.apply_calibration(session_id, label, body.us_n_mm2, body.k, None,
                                       body.provenance)
    result = run_fit(body.fit, material.k)  # fit="us" holds the material's K
    answer = plane.apply_calibration(session_id, label, result["us"], result["k"],
                                     summary_of(result), body.provenance)
    return {**answer, "result": result}


@router.get("/sessions/{session_id}/calibration")
def get_calibration(plane: PlaneDep, session_id: int = SessionPath) -> dict:
    """The calibrations applied to this session, by material label (latest per label), each
    with the material's values now and ``in_force``: false once the material was set another
    way (a PATCH, another calibration of its Us or K)."""
    s = plane.get(session_id)
    out = {}
    for label, record in sorted(s.calibrations.items()):
        now = s.materials[label] if s.materials is not None and label in s.materials else None
        current = None if now is None else {"us_n_mm2": now.us_n_mm2, "k": now.k}
        out[str(label)] = {**record, "current": current, "in_force": current is not None
                           and current == {"us_n_mm2": record["us_n_mm2"], "k": record["k"]}}
    return out
