"""A profilometer measurement diagnosed in the camera's frame (``doe diagnose --frame camera``,
``doe demo``): the comparison's registration starts :func:`~metrology.diagnosis.camera_diagnosis.diagnose_camera`'s
placement, and the data stay as read.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from doedesign.errors import DoeError
from metrology.diagnosis import engine as dg
from metrology.diagnosis.camera_diagnosis import diagnose_camera
from metrology.diagnosis.camera_nuisance import InstrumentFamily
from metrology.matching.transfer import LateralTransfer

if TYPE_CHECKING:
    from doedesign.design import Design
    from metrology.diagnosis.budget import Deadline
    from metrology.formats.measurement import Measurement
    from metrology.matching.compare import Comparison

__all__ = ["diagnose_camera_measurement"]


def diagnose_camera_measurement(design: Design, measurement: Measurement, depths_m: Sequence[float] | None = None,
                                candidates: Sequence[str] | None = None, threshold: float = dg.DEFAULT_THRESHOLD,
                                window_px: int = 160, source: str = "measurement", force: bool = False,
                                comparison: Comparison | None = None,
                                transfer: LateralTransfer | None = None, batwing: Sequence[float] | None = None,
                                limit: Deadline | None = None) -> tuple[dg.Diagnosis, dict[str, Any]]:
    """Diagnose a profilometer measurement in the camera's frame (``doe diagnose --frame camera``
    and ``doe demo``): the comparison's registration starts the placement, the data stay as read.

    Parameters
    ----------
    design : Design
    measurement : Measurement
        As read by :func:`metrology.formats.readers.read_measurement`.
    depths_m : sequence of float, optional
        Nominal etch depths per mask (the ideal model).
    candidates : list of str, optional
    threshold : float
    window_px : int
        Camera pixels per side of the window diagnosed.
    source : str
        Name of the measurement in error messages (its file).
    force : bool
        Diagnose even when the measurement matches the design poorly.
    comparison : Comparison, optional
        :func:`~metrology.matching.compare.compare_measurement` of the same measurement and
        design, if already made (its camera-frame placement starts the fit).
    transfer : LateralTransfer, optional
        The instrument's calibrated lateral transfer, held fixed (default: fitted).
    batwing, limit
        As for :func:`~metrology.diagnosis.camera_diagnosis.diagnose_camera` (no limit by default).

    Returns
    -------
    (Diagnosis, dict)
        The diagnosis and its inputs (frame, window, refined placement with uncertainties,
        excluded pixels, registration correlation, nominal depths, match).
    """
    from doedesign.levels import design_levels
    from doedesign.progress import Progress
    from masks.decompose import process_depths_m
    from metrology.matching.compare import compare_measurement

    if window_px < 16:
        raise DoeError(f"--window-px must be at least 16, got {window_px}")
    comp = comparison
    if comp is None:
        with Progress(1, desc="doe diagnose: comparison") as bar:
            bar.stage("registration, levelling, the instrument's fit on the whole field")
            try:
                comp = compare_measurement(measurement, design, force=force, transfer=transfer, texture=False)
            except DoeError as exc:
                raise DoeError(f"{source}: {exc}") from None
            bar.update(1, "done")
    depths = process_depths_m(design, depths_m, source)
    # The comparison's placement was refined in the camera's frame (same measurement model).
    fit = comp.instrument_fit
    stage = (comp.instrument_family or {}).get("stage", {})
    family = (InstrumentFamily(fit.transfer, fit.batwing, stage.get("criterion_changes", {}))
              if transfer is None and stage.get("members") else None)
    diag = diagnose_camera(design_levels(design), design.pitch_m, measurement.height_m, fit.placement,
                           depths_m=depths, candidates=candidates, threshold=threshold, window_px=window_px,
                           screen=(comp.fitted_params(), fit.blur_sigma_m), transfer=transfer,
                           batwing=batwing, limit=limit, family=family)
    return diag, {"frame": "camera", "window_camera_px": diag.window_camera_px, "placement": diag.placement,
                  "excluded_pixels": diag.excluded_pixels,
                  "registration_ncc": getattr(comp.registration, "match_ncc", None), "nominal_depths_m": depths,
                  "match": comp.match}
