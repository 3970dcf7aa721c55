"""Fault codes: what a cycle that ended without figures tells the robot (docs/plc.md) and the record.

An error that ends a cycle (a camera that stopped answering, a capture the analysis refused, a worker that
died...) becomes a fault *kind* and its reason code (:data:`~sofast_station.devices.protocols.FAULT_CODES`,
the PLC's register); the record's first reason starts with the kind (``"camera: no frame within 2 s"``), so
the kind can be read back from any journaled record (:func:`fault_kind`).
"""

from __future__ import annotations

from ..calibrate.errors import StaleCalibrationError
from ..devices.protocols import FAULT_CODES
from ..errors import (AnalysisTimeout, CameraError, CaptureError, DisplayError, GeometryError, StationError,
                      UnknownRecipeError, WorkerDied)

#: The fault kind of an exception that ended a cycle: the first class it is an instance of.
FAULT_KINDS = ((StaleCalibrationError, "calibration"), (AnalysisTimeout, "timeout"), (CameraError, "camera"),
               (DisplayError, "display"), (CaptureError, "capture"), (GeometryError, "geometry"),
               (UnknownRecipeError, "recipe"), (WorkerDied, "worker"), (StationError, "analysis"))


def fault_code_for(exc: BaseException) -> tuple[int, str]:
    """Reason code and kind for an exception that ended a cycle ("internal", 99, for anything that is not a
    StationError: a bug)."""
    kind = next((kind for cls, kind in FAULT_KINDS if isinstance(exc, cls)), "internal")
    return FAULT_CODES[kind], kind


def fault_reason(exc: BaseException) -> tuple[int, str]:
    """Reason code and the record's reason (``"kind: message"``) for an exception that ended a cycle."""
    code, kind = fault_code_for(exc)
    return code, f"{kind}: {exc}"


def fault_kind(record: dict) -> str:
    """The kind of a faulted record: the part of its first reason before the colon ("camera", ...)."""
    reasons = record.get("reasons") or []
    head = str(reasons[0]).split(":", 1)[0].strip() if reasons else ""
    return head if head and len(head) <= 20 and " " not in head else "other"
