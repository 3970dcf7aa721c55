"""What a report can draw: a data dump (reprocessed from its raw frames) or an OpenCSP measurement.

``opencsp:DIR`` names a folder in the layout of OpenCSP's test data (``fixtures/opencsp/test_data``);
anything else is a dump. Both come back as a :class:`Measured` with the analysis, a record and the design.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from ..archive.dumps import read_dump
from ..errors import ReportError
from ..interop.opencsp import opencsp_test_data_paths, read_opencsp
from .reprocess import reprocess_dump

log = logging.getLogger(__name__)


class _NoOverrides:
    def to_dict(self) -> dict:
        return {}


@dataclass
class Measured:
    """One measured facet ready to draw (duck-typed like a reprocessed dump's result)."""

    path: Path
    analysis: object
    record: dict
    design: object
    overrides: object = field(default_factory=_NoOverrides)
    kind: str = "dump"


def is_opencsp(spec: str) -> bool:
    return str(spec).startswith("opencsp:")


def check_measured(spec: str) -> None:
    """Refuse at once what :func:`load_measured` could not read: a dump that is missing or unreadable (its
    metadata read, not its frames), or a folder not in OpenCSP's test-data layout (DumpError or ReportError
    naming it), so that a command given two inputs does not reprocess the first before refusing the second."""
    if is_opencsp(spec):
        root = Path(str(spec)[len("opencsp:"):])
        missing = [str(p) for p in opencsp_test_data_paths(root).values() if not p.exists()]
        if missing:
            raise ReportError(f"{root} is not a folder in OpenCSP's test-data layout: missing {', '.join(missing)}")
        return

    read_dump(spec, load_frames=False, require_result=False)


def load_measured(spec: str, overrides=None, focal_length_m: float = 100.0) -> Measured:
    """A dump (reprocessed with *overrides*) or ``opencsp:DIR`` (analysed with *focal_length_m*)."""
    if is_opencsp(spec):
        root = Path(str(spec)[len("opencsp:"):])
        check_measured(spec)
        m = read_opencsp(**opencsp_test_data_paths(root), focal_length_m=focal_length_m)
        a = m.analyse(robust=True, uncertainty=m.uncertainty)      # every figure with its U (docs/opencsp.md)
        rec = {"serial": m.name, "facet": m.design.name, "time": m.date, "station": "OpenCSP import",
               **a.figures}
        return Measured(root, a, rec, m.design, kind="opencsp")

    res = reprocess_dump(spec, overrides)
    if res.u_missing and res.overrides.empty:
        # an older dump: the figures are the line's, their U the re-analysis's own (reprocess lists them)
        log.warning("%s: the U shown are the re-analysis's, not the line's: the dump does not keep %s the line's U "
                    "came from ('reprocess %s' shows both)", spec, " nor ".join(res.u_missing), spec)
    if res.analysis is None:
        raise ReportError(f"cannot draw {spec}: the analysis refused the capture "
                          f"({'; '.join(res.record.get('reasons', []))})")
    return Measured(Path(spec), res.analysis, res.record, res.design, res.overrides, "dump")
