"""Excel workbooks: one row per facet, one workbook per day (or shift), written atomically.

A workbook lives in ``data_dir/archive/`` and is named from the record's local date (the date in the
record's own UTC offset): ``results-2026-11-25.xlsx``, or per shift ``results-2026-11-25-shift0600.xlsx``
(a night shift that crosses midnight belongs to the day it started). When a workbook reaches Excel's row
limit (1,048,576 rows with the header) the rows continue in ``results-2026-11-25-part2.xlsx`` and so on.

Every row holds ``cycle_id``, ``serial``, ``time``, ``verdict``, ``reasons``, ``dump_file``, then every
other figure of the record flattened to dotted column names (``slope_rms_mrad.design.x``). What a plant
needs to work with the book in Excel:

- ``time`` is an Excel date and time (the record's local wall-clock time; its UTC offset is the column
  ``utc_offset``), so it sorts, filters and plots as a date;
- every figure is a number cell with a number format; a missing or null value is an empty cell;
- lists are readable text, items separated by ``; `` (``reasons``, principal focal lengths, terms);
- ``dump_file`` names the facet's HDF5 data dump when one was written or is on its way;
- the sheet ``units`` gives the unit of every column (the column names also end in their unit:
  ``_m``, ``_mrad``, ``_per_m``, ``_s``, ``_dn``, ``_px``);
- ``truth.*`` columns (the twin's ground truth) exist only for rows of the simulated station: a hardware
  station's records have no truth.

A record with a figure the book has no column for adds the column at the right.

Safety (docs/conventions.md#archives):

- a save writes a temporary file in the same folder, flushes and fsyncs it, renames it over the book
  (``os.replace``) and fsyncs the folder: the book under its name is always a complete, valid file;
- before writing, the cycle ids the book already holds are read, so a crash after the rename but before
  the journal was marked never duplicates a row;
- when a save fails (the book is open in Excel on a share: ``PermissionError``; the disk is full:
  ``OSError ENOSPC``) the temporary file is removed and the rows stay pending in the journal for the next
  attempt;
- all pending rows of a book go in one save: a save writes the whole part again, streamed (openpyxl's
  write-only mode) from the journal's records of the rows it holds, a hundred at a time, so neither its
  memory nor the archiver's grows with the rows of the part (a part holds ``max_rows`` rows, 1000 on a
  station: bounded work); rows of the file that the journal does not know are kept as they were.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ArchiveError
from ..files import fsync_dir, json_ready, safe_name, temp_path_for
from ..gum import u_decimals
from ..times import parse_time
from ._common import fault_point
from .dumps import dump_name
from .journal import Journal, JournalRow

log = logging.getLogger(__name__)

#: Excel's row limit per sheet, header included (monkeypatched small by the rollover test).
EXCEL_MAX_ROWS = 1_048_576

#: The columns every workbook starts with, in this order.
FIRST_COLUMNS = ("cycle_id", "serial", "time", "verdict", "reasons", "dump_file")

#: Record entries that get no workbook columns.
NOT_IN_WORKBOOK = ("uncertainty_budget",)

#: Title of the results sheet.
SHEET_TITLE = "results"

#: Excel refuses cells longer than this many characters.
_MAX_CELL_CHARS = 32_767

_PERIODS = ("day", "shift")


@dataclass(frozen=True)
class WorkbookSettings:
    """How results are split into workbooks.

    Attributes
    ----------
    period : str
        ``"day"`` (one book per local date) or ``"shift"`` (one per shift).
    shift_starts_h : tuple of float
        Local hours at which shifts start, increasing, within [0, 24); used when ``period == "shift"``.
    prefix : str
        File name prefix.
    max_rows : int or None
        Data rows per workbook part; None: Excel's limit minus the header row.
    """

    period: str = "day"
    shift_starts_h: tuple[float, ...] = (6.0, 14.0, 22.0)
    prefix: str = "results"
    max_rows: int | None = None

    def __post_init__(self):
        if self.period not in _PERIODS:
            raise ArchiveError(f"workbook period must be one of {_PERIODS}, got {self.period!r}")
        starts = tuple(float(h) for h in self.shift_starts_h)
        if not starts or any(not 0 <= h < 24 for h in starts) or any(b <= a for a, b in zip(starts, starts[1:])):
            raise ArchiveError(f"shift_starts_h must be increasing local hours in [0, 24), got {list(starts)}")
        object.__setattr__(self, "shift_starts_h", starts)
        if self.max_rows is not None and int(self.max_rows) < 1:
            raise ArchiveError(f"workbook max_rows must be at least 1, got {self.max_rows}")

    def rows_per_part(self) -> int:
        """Data rows a workbook part may hold."""
        limit = EXCEL_MAX_ROWS - 1
        return min(int(self.max_rows), limit) if self.max_rows else limit


@dataclass
class WorkbookReport:
    """What one :func:`write_pending` call did.

    Attributes
    ----------
    written : dict
        Workbook path -> number of rows added.
    already_present : int
        Pending rows found already in their book (a crash after the rename) and only marked.
    waiting : int
        Rows left pending because their book could not be saved.
    errors : dict
        Workbook path -> the error that kept its rows pending.
    """

    written: dict = field(default_factory=dict)
    already_present: int = 0
    waiting: int = 0
    errors: dict = field(default_factory=dict)

    @property
    def rows_written(self) -> int:
        return sum(self.written.values())


# -- rows -------------------------------------------------------------------------------------------
def _flatten(prefix: str, value, out: dict) -> None:
    if isinstance(value, dict):
        if not value and prefix:
            out[prefix] = None
        for k, v in value.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    else:
        out[prefix] = value


def _list_text(items: list) -> str:
    """A list as text a person reads: scalars joined by "; ", anything nested as JSON."""
    if all(v is None or isinstance(v, (str, int, float, bool)) for v in items):
        return "; ".join("" if v is None else f"{v:.10g}" if isinstance(v, float) else str(v) for v in items)
    return json.dumps(items, ensure_ascii=False)


def excel_time(time_iso) -> tuple:
    """(naive local datetime for an Excel date cell, the UTC offset as text ``+01:00``) of an ISO time."""
    if time_iso is None:
        return None, None
    try:
        t = parse_time(time_iso)
    except (TypeError, ValueError):
        return time_iso, None                       # not a time: keep the text as it is
    off = t.utcoffset() or _dt.timedelta(0)
    sign = "-" if off < _dt.timedelta(0) else "+"
    minutes = abs(int(off.total_seconds())) // 60
    # Excel keeps milliseconds: drop the rest so a read-back equals what is shown
    offset = f"{sign}{minutes // 60:02d}:{minutes % 60:02d}"
    return t.replace(tzinfo=None, microsecond=t.microsecond // 1000 * 1000), offset


def flatten_record(cycle_id: str, record: dict, dump_file: str | None = None, json_safe: bool = False) -> dict:
    """The workbook row of a record: column name -> cell value.

    ``cycle_id``, ``serial``, ``time`` (a naive local datetime), ``verdict``, ``reasons``, ``dump_file``
    come first, then ``utc_offset`` and every other entry in record order, nested dicts flattened to
    dotted names. Lists become readable text (:func:`_list_text`); NaN, infinities and None become None
    (an empty cell). The uncertainty budget (the same table for every facet of a recipe, kept in the
    journal and the dumps) gets no columns; each figure's ``_U`` does. *json_safe*: the record is as
    JSON holds it already (a journal row's), so its conversion (:func:`json_ready`) is skipped.
    """
    rec = {k: v for k, v in record.items() if k not in NOT_IN_WORKBOOK}
    if not json_safe:
        rec = json_ready(rec)
    flat: dict = {}
    _flatten("", {k: v for k, v in rec.items() if k not in FIRST_COLUMNS}, flat)
    when, offset = excel_time(rec.get("time"))
    row = {"cycle_id": cycle_id, "serial": rec.get("serial"), "time": when,
           "verdict": rec.get("verdict"), "reasons": rec.get("reasons", []), "dump_file": dump_file,
           "utc_offset": offset}
    row.update(flat)
    return {k: (_list_text(v) if isinstance(v, list) else v) for k, v in row.items()}


#: A heliostat's record: what its facets' rows leave out (said once in the journal and the dump).
_HELIOSTAT_NOT_IN_ROWS = ("facets", "canting_instructions", "pictures")


def flatten_rows(cycle_id: str, record: dict, dump_file: str | None = None, json_safe: bool = False) -> list[dict]:
    """The workbook rows of a record: one (:func:`flatten_record`), or for a heliostat's record
    (``facets``) one per facet: its ``serial`` (the heliostat's and the facet's label), ``verdict`` and
    ``reasons``, ``heliostat_serial``, ``heliostat_verdict``, ``facet_label``, its own figures (its canting
    among them), then the heliostat's figures (``heliostat.*``, ``optics.*``) beside them, so a facet's row
    reads on its own and the rows of a heliostat filter together."""
    facets = record.get("facets")
    if not isinstance(facets, list):
        return [flatten_record(cycle_id, record, dump_file, json_safe)]
    shared = {k: v for k, v in record.items() if k not in _HELIOSTAT_NOT_IN_ROWS}
    rows = []
    for f in facets:
        own = {k: v for k, v in f.items() if k not in ("serial", "verdict", "reasons", "label")}
        rec = {**shared, "serial": f.get("serial"), "verdict": f.get("verdict"), "reasons": f.get("reasons", []),
               "heliostat_serial": record.get("serial"), "heliostat_verdict": record.get("verdict"),
               "facet_label": f.get("label"), **own,
               "heliostat_reasons": record.get("reasons", [])}
        rows.append(flatten_record(cycle_id, rec, dump_file, json_safe))
    return rows


def column_unit(name: str) -> str:
    """The unit of a workbook column, from its name's suffix (the record's naming convention)."""
    n = name.lower()
    last = n.rsplit(".", 1)[-1]
    if n == "time":
        return "local date and time (see utc_offset)"
    if n.startswith("slope_rms_mrad") or n.startswith("truth.slope_rms_mrad") or "boresight_mrad" in n \
            or "optical_tilt_mrad" in n or n.endswith("placement.mrad"):
        return "mrad"
    if n.endswith("placement.mm"):
        return "mm"
    for suffix, unit in (("_mrad_per_m", "mrad/m"), ("_per_m", "1/m"), ("_mrad", "mrad"), ("_dn", "DN"),
                         ("_px", "px"), ("_rad", "rad"), ("_m", "m"), ("_s", "s"), ("_gb", "GB")):
        if last.endswith(suffix) or n.endswith(suffix):
            return unit
    if n.startswith("timings_s.") or ".timings_s." in n:
        return "s"
    if "fraction" in n or "agreement" in n:
        return "1 (fraction)"
    if n.startswith("coefficients.") and last in ("a", "b", "e"):
        return "1/m"
    if n.startswith("coefficients."):
        return "1 (slope)"
    return ""


def uncertainty_column(column: str, row: dict) -> str | None:
    """The column of *row* that holds the expanded uncertainty of *column*: the record's ``NAME_U`` sibling at
    the figure's level (``focal_length_x_m_U``, ``slope_rms_mrad_U.design.x``, ``optics.intercept_U``), or
    None."""
    parts = column.split(".")
    for i in range(len(parts)):
        name = ".".join(parts[:i] + [parts[i] + "_U"] + parts[i + 1:])
        if name in row:
            return name
    return None


def shown_decimals(row: dict) -> dict:
    """Column -> decimals its cell shows, for each figure of *row* with an expanded uncertainty and for that
    U's own column: the decimals of U's two significant digits (GUM 7.2.6), the place the console, the page
    and the certificate write the figure to (:func:`~sofast_station.gum.with_u`); the cell keeps every digit."""
    out = {}
    for name, value in row.items():
        u_name = uncertainty_column(name, row) if isinstance(value, float) else None
        d = None if u_name is None else u_decimals(row[u_name])
        if d is not None:
            out[name] = out[u_name] = max(d, 0)       # a U of 100 or more: a format cannot round to tens
    return out


def number_format(column: str, value, decimals: int | None = None) -> str | None:
    """Excel number format for a cell of *column* holding *value* (None: leave General); *decimals* (a figure
    with its U: :func:`shown_decimals`) fixes the places shown."""
    if isinstance(value, _dt.datetime):
        return "yyyy-mm-dd hh:mm:ss"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if isinstance(value, int):
        return "0"
    if decimals is not None:
        return "0." + "0" * decimals if decimals > 0 else "0"
    name = column.lower()
    if name.startswith("timings_s."):
        return "0.000"
    if "coefficients" in name:
        return "0.000000E+00"
    if "curvature" in name:
        return "0.000000"
    if "mrad" in name:
        return "0.0000"
    if "fraction" in name or "agreement" in name:
        return "0.0000"
    if name.endswith("_dn"):
        return "0.00"
    if name.endswith("_m") or "_m." in name or name.endswith("exposure_s"):
        return "0.000000"
    if name.endswith("_px") or name.endswith("_s"):
        return "0.000"
    return "0.000000" if 1e-3 <= abs(value) < 1e6 or value == 0 else "0.000000E+00"


def row_dump_file(row: JournalRow) -> str | None:
    """The file name of a journal row's data dump: written, or requested and on its way; else None."""
    if row.dump_path:
        return Path(row.dump_path).name
    if row.dump_requested and not row.dump_error:
        try:
            return dump_name(row.serial, row.time, row.cycle_id)
        except (TypeError, ValueError):
            return None
    return None


def _cell_value(value):
    if isinstance(value, str):
        # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
        from openpyxl.cell.cell import ILLEGAL_CHARACTERS_RE
        value = ILLEGAL_CHARACTERS_RE.sub("\N{REPLACEMENT CHARACTER}", value)
        if len(value) > _MAX_CELL_CHARS:
            value = value[:_MAX_CELL_CHARS - 1] + "\N{HORIZONTAL ELLIPSIS}"
    return value


# -- naming -----------------------------------------------------------------------------------------
def period_key(time_iso: str, settings: WorkbookSettings = WorkbookSettings()) -> str:
    """The period a record belongs to, from its local date and time: ``2026-11-25`` or
    ``2026-11-25-shift0600``."""
    t = parse_time(time_iso)
    if settings.period == "day":
        return t.date().isoformat()
    hours = t.hour + t.minute / 60 + t.second / 3600 + t.microsecond / 3.6e9
    starts = settings.shift_starts_h
    before = [h for h in starts if h <= hours]
    if before:
        start, day = before[-1], t.date()
    else:                                    # before the first shift: the previous day's last shift
        start, day = starts[-1], t.date() - _dt.timedelta(days=1)
    hh, mm = int(start), int(round((start - int(start)) * 60))
    return f"{day.isoformat()}-shift{hh:02d}{mm:02d}"


def workbook_path(folder: Path, key: str, part: int = 1, prefix: str = "results") -> Path:
    """File of part *part* (1, 2, ...) of the workbook of period *key*."""
    base = f"{safe_name(prefix)}-{key}"
    return Path(folder) / (f"{base}.xlsx" if part == 1 else f"{base}-part{part}.xlsx")


def workbook_parts(folder: Path, key: str, prefix: str = "results") -> list[Path]:
    """The existing parts of a period's workbook, in part order."""
    parts = []
    part = 1
    while True:
        path = workbook_path(folder, key, part, prefix)
        if not path.exists():
            # a missing part in the middle would hide later ones: look a little further
            if not any(workbook_path(folder, key, p, prefix).exists() for p in range(part + 1, part + 4)):
                break
        else:
            parts.append(path)
        part += 1
    return parts


def _part_number(folder: Path, key: str, prefix: str, path: Path) -> int:
    part = 1
    while workbook_path(folder, key, part, prefix) != path:
        part += 1
    return part


# -- files ------------------------------------------------------------------------------------------
#: Journal rows fetched at a time while a part is written (bounds the records held at once).
_FETCH_ROWS = 100

#: Widths of the first columns (cycle_id, serial, time, verdict, reasons, dump_file), characters.
_FIRST_WIDTHS = (30, 14, 20, 9, 40, 44)


@dataclass
class _PartScan:
    """What a workbook part on the disk holds: its header and its rows' cycle ids, in sheet order."""

    path: Path
    header: list
    ids: list

    @property
    def n_rows(self) -> int:
        return len(self.ids)


def _open_read_only(path: Path):
    # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
    from openpyxl import load_workbook

    try:
        return load_workbook(path, read_only=True)
    except OSError:
        raise
    except Exception as exc:    # zipfile.BadZipFile, KeyError, InvalidFileException, XML errors...
        raise ArchiveError(f"workbook {path} is not a readable .xlsx file ({type(exc).__name__}: {exc})") from exc


def _results_sheet(wb):
    return wb[SHEET_TITLE] if SHEET_TITLE in wb.sheetnames else wb.worksheets[0]


def scan_part(path: Path) -> _PartScan:
    """The header and cycle ids of a results workbook part, read in streaming mode (nothing per cell kept).

    Raises
    ------
    OSError
        When the file cannot be read (permissions, a share that went away): a transient condition.
    ArchiveError
        When the file is not a readable results workbook.
    """
    path = Path(path)
    wb = _open_read_only(path)
    try:
        ws = _results_sheet(wb)
        header = [h for h in next(ws.iter_rows(max_row=1, values_only=True), ()) if h is not None]
        if not header or header[0] != "cycle_id":
            raise ArchiveError(f"workbook {path} does not start with a cycle_id column; it is not a results "
                               "workbook of this station")
        # (a heliostat's cycle has a row per facet: its id once, in sheet order)
        ids = list(dict.fromkeys(v for (v,) in ws.iter_rows(min_row=2, max_col=1, values_only=True) if v is not None))
    except (OSError, ArchiveError):
        raise
    except Exception as exc:    # a damaged sheet inside a readable zip
        raise ArchiveError(f"workbook {path} is not a readable .xlsx file ({type(exc).__name__}: {exc})") from exc
    finally:
        wb.close()
    return _PartScan(path, header, [str(i) for i in ids])


#: The parts this process wrote or read last: path -> (the file's identity, header, cycle ids), so that the
#: next pass need not read back what it has just written (about a third of a pass's CPU time on a full
#: part). A file changed since, by anyone (another inode, size or modification time), is read again.
_WRITTEN: dict = {}
_WRITTEN_MAX = 16


def _identity(path: Path) -> tuple:
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


def _remember(scan: _PartScan, identity: tuple | None = None) -> None:
    """Note what *scan*'s part holds: just written by this process, or read when the file was *identity*."""
    key = str(scan.path)
    _WRITTEN.pop(key, None)
    try:
        _WRITTEN[key] = (identity or _identity(scan.path), tuple(scan.header), tuple(scan.ids))
    except OSError:
        return
    while len(_WRITTEN) > _WRITTEN_MAX:
        _WRITTEN.pop(next(iter(_WRITTEN)))


def _recall(path: Path) -> _PartScan | None:
    """The scan of a part as this process wrote it, when the file is still that one; else None."""
    known = _WRITTEN.get(str(path))
    try:
        if known is None or known[0] != _identity(path):
            return None
    except OSError:
        return None
    return _PartScan(Path(path), list(known[1]), list(known[2]))


def _file_rows(path: Path, wanted: set) -> dict:
    """Cycle id -> [{column: value}, ...] of the rows of *path* whose id is in *wanted* (rows the journal
    lacks; a heliostat's cycle has several)."""
    wb = _open_read_only(path)
    try:
        rows = _results_sheet(wb).iter_rows(values_only=True)
        header = list(next(rows, ()))
        out: dict = {}
        for v in rows:
            if v and v[0] is not None and str(v[0]) in wanted:
                out.setdefault(str(v[0]), []).append({h: x for h, x in zip(header, v)
                                                      if h is not None and x is not None})
        return out
    finally:
        wb.close()


def _cell(ws, column: str, value, decimals: int | None = None):
    """What goes into a write-only sheet for *value* in *column* (shown to *decimals* places when given): the
    value, or a styled cell."""
    # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
    from openpyxl.cell import WriteOnlyCell

    value = _cell_value(value)
    fmt = number_format(column, value, decimals)
    if isinstance(value, str):
        if value[:1] in ("=", "#"):
            cell = WriteOnlyCell(ws, value)
            cell.data_type = "s"     # text from outside (a serial "=HYPERLINK(...)", "#N/A") is never a formula
            return cell
        return value
    if fmt:
        cell = WriteOnlyCell(ws, value)
        cell.number_format = fmt
        return cell
    return value


class _PartWriter:
    """Writes one workbook part whole, in openpyxl's write-only (streaming) mode, from the journal.

    A part is regenerated on every save rather than loaded and appended to: rows are read from the
    journal (the source of truth, which holds every row's record) a few at a time and streamed into the
    sheet, so the memory a save needs does not grow with the rows the part holds (openpyxl's normal mode
    keeps every cell of the loaded part as an object, about 80 kB a row of 236 columns).

    Parameters
    ----------
    path : Path
        The part's file.
    slots : list of str
        The cycle ids of its rows, in order.
    journal : Journal or None
        Where the records of *slots* are read (rows given in *given* excepted).
    given : dict, optional
        Cycle id -> JournalRow already at hand (the rows being added; an export's rows).
    header : list of str, optional
        The part's columns so far (its file's header): kept in their order, new ones added at the right.
    foreign : dict, optional
        Cycle id -> [{column: value}, ...] of rows of the old file the journal does not know (a journal
        started afresh beside an existing workbook): kept as they were.
    """

    def __init__(self, path: Path, slots: list, journal: Journal | None, given: dict | None = None,
                 header: list | None = None, foreign: dict | None = None):
        self.path = Path(path)
        self.slots = slots
        self.journal = journal
        self.given = given or {}
        self.header = list(header) if header else list(FIRST_COLUMNS)
        self.foreign = foreign or {}

    def _flat_rows(self):
        """Every slot's row as {column: value}, in order, fetching journal rows _FETCH_ROWS at a time."""
        for i in range(0, len(self.slots), _FETCH_ROWS):
            chunk = self.slots[i:i + _FETCH_ROWS]
            need = [c for c in chunk if c not in self.given and c not in self.foreign]
            fetched = self.journal.rows_by_ids(need) if need and self.journal is not None else {}
            for cycle_id in chunk:
                row = self.given.get(cycle_id) or fetched.get(cycle_id)
                if row is not None:           # (a heliostat's cycle: one row per facet)
                    yield from flatten_rows(row.cycle_id, row.record, row_dump_file(row), json_safe=True)
                elif cycle_id in self.foreign:
                    yield from self.foreign[cycle_id]
                else:
                    raise ArchiveError(f"workbook {self.path}: cycle {cycle_id} is neither in the journal nor in "
                                       "the part")
            del fetched

    def save(self) -> list:
        """Write the part (atomically, :func:`save_atomic`); returns its header."""
        # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
        # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
        # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
        # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
        from openpyxl import Workbook
        from openpyxl.cell import WriteOnlyCell
        from openpyxl.styles import Font
        from openpyxl.utils import get_column_letter

        columns = {name: i for i, name in enumerate(self.header)}
        n_rows = 0
        for flat in self._flat_rows():                      # first pass: the columns (a sheet streams its
            n_rows += 1                                     # header first)
            for name in flat:
                if name not in columns:
                    columns[name] = len(self.header)
                    self.header.append(name)
        wb = Workbook(write_only=True)
        ws = wb.create_sheet(SHEET_TITLE)
        ws.freeze_panes = "B2"
        for i, width in enumerate(_FIRST_WIDTHS, start=1):
            ws.column_dimensions[get_column_letter(i)].width = width
        ws.auto_filter.ref = f"A1:{get_column_letter(max(len(self.header), 1))}{n_rows + 1}"
        bold = Font(bold=True)

        def heading(text):
            cell = WriteOnlyCell(ws, text)
            cell.font = bold
            return cell

        try:
            _stream_beside(ws, self.path)                   # after the sheet's settings: they head its stream
            ws.append([heading(name) for name in self.header])
            width = len(self.header)
            for flat in self._flat_rows():                  # second pass: the rows, streamed to the sheet
                cells = [None] * width
                shown = shown_decimals(flat)
                for name, value in flat.items():
                    # a column the first pass did not see: the row was amended (a late result) between the
                    # passes; its journal row changed version, so it stays pending and is written whole again
                    if value is not None and name in columns:
                        cells[columns[name]] = _cell(ws, name, value, shown.get(name))
                ws.append(cells)
            us = wb.create_sheet("units")
            us.column_dimensions["A"].width = 44
            us.column_dimensions["B"].width = 30
            _stream_beside(us, self.path)
            us.append([heading("column"), heading("unit")])
            for name in self.header:
                us.append([name, column_unit(name)])
            save_atomic(wb, self.path)
        finally:
            _drop_stream_files(wb)
        return self.header


def _stream_beside(ws, path: Path) -> None:
    """Stream write-only sheet *ws* into a temporary file beside *path*, not into the system's temp folder.

    Call it after the sheet's settings (freeze panes, widths, filter) and before its first row: the
    stream begins with them.

    openpyxl streams each sheet into ``/tmp/openpyxl.*`` until the save; a writer killed meanwhile leaves
    that file (tens of MB for a full part) where nothing of ours ever looks. Named as our other temporary
    files (``.<part>.sheet.<pid>.<random>.tmp``), it is removed at the next start like them. openpyxl has
    no public option for it: its sheet writer takes the file as *out* and registers it for its own
    clean-up (the test ``test_a_save_streams_its_sheets_beside_the_part`` guards this).
    """
    # lazy: openpyxl costs ~135 ms CPU; every user of the journal loads this module (archive/__init__.py)
    from openpyxl.worksheet._writer import ALL_TEMP_FILES, WorksheetWriter

    out = temp_path_for(path.with_name(path.name + ".sheet"))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.touch()
    ALL_TEMP_FILES.append(str(out))
    ws._writer = WorksheetWriter(ws, out=str(out))
    ws._writer.write_top()


def _drop_stream_files(wb) -> None:
    """Remove the temporary files of a write-only workbook's sheets that were not saved (an error)."""
    for ws in getattr(wb, "_sheets", ()):
        writer = getattr(ws, "_writer", None)
        out = getattr(writer, "out", None)
        if isinstance(out, str) and os.path.exists(out):
            for gen in (getattr(ws, "_rows", None), writer):   # the rows' generator first, then the file's
                try:
                    if gen is not None:
                        gen.close()
                except Exception:  # a half-written sheet's stream; its file goes anyway
                    pass
            try:
                writer.cleanup()
            except (OSError, ValueError):
                pass


def _save_to(wb, fileobj) -> None:
    """Serialise *wb* into an open binary file (a seam for the disk-full test)."""
    wb.save(fileobj)


def save_atomic(wb, path: Path) -> None:
    """Save an openpyxl workbook so that *path* is always either the old or the new complete file.

    Writes ``.<name>.<pid>.<random>.tmp`` in the same folder, flushes and fsyncs it, renames it over
    *path* and fsyncs the folder. On any failure the temporary file is removed and the error raised.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_for(path)
    try:
        with open(tmp, "wb") as fh:
            _save_to(wb, fh)
            fh.flush()
            os.fsync(fh.fileno())
        fault_point("workbook-temp-written")
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)
        except OSError as exc:
            log.warning("could not remove the temporary workbook %s: %s", tmp, exc)
        raise
    fsync_dir(path.parent)
    fault_point("workbook-renamed")


def read_workbook(path: str | Path) -> list[dict]:
    """The data rows of a results workbook as dicts (column name -> value; empty cells omitted)."""
    path = Path(path)
    wb = _open_read_only(path)
    try:
        rows = _results_sheet(wb).iter_rows(values_only=True)
        header = list(next(rows, ()))
        out = []
        for values in rows:
            if not values or values[0] is None:
                continue
            out.append({h: v for h, v in zip(header, values) if h is not None and v is not None})
        return out
    finally:
        wb.close()


# -- writing rows -----------------------------------------------------------------------------------
def _quarantine(path: Path) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%dT%H%M%S")
    aside = path.with_name(f"{path.stem}.corrupt-{stamp}{path.suffix}")
    os.replace(path, aside)
    log.error("workbook %s was unreadable; moved aside to %s and rebuilt from the journal", path, aside)
    return aside


def _rebuild(path: Path, journal: Journal) -> _PartScan:
    """Set a damaged part aside and rebuild it from the journal rows recorded as written to it."""
    _quarantine(path)
    ids = journal.ids_in_workbook(path)
    scan = _PartScan(path, _PartWriter(path, ids, journal).save(), ids)
    _remember(scan)
    return scan


def _scan(path: Path, journal: Journal | None) -> _PartScan:
    """Scan a part (or recall it, unchanged since this process wrote or read it); a damaged one (by something
    else than this software) is rebuilt from the journal."""
    recalled = _recall(path)
    if recalled is not None:
        return recalled
    try:
        identity = _identity(path)             # before the read: a change while reading is read again later
        scan = scan_part(path)
        _remember(scan, identity)
        return scan
    except ArchiveError:
        if journal is None:
            raise
        return _rebuild(path, journal)


def _is_late(row) -> bool:
    """Whether a journal row (JournalRow or PendingRow) is an amended late result."""
    late = getattr(row, "late", None)
    return bool(row.record.get("late")) if late is None else late


def _rewrite(scan: _PartScan, journal: Journal | None, given: dict, new: list | None = None) -> None:
    """Write *scan*'s part again with its rows (their records as the journal holds them now, or as *given*)
    followed by the *new* rows; rows of the file the journal does not know are kept as they were. Rows
    given without their record (PendingRow) are read from the journal as the part is written."""
    new = new or []
    given = {k: r for k, r in given.items() if hasattr(r, "record")}
    known = set(given)
    if journal is not None:
        unknown = [i for i in scan.ids if i not in known]
        for k in range(0, len(unknown), 500):
            known.update(journal.known_ids(unknown[k:k + 500]))
    lost = {i for i in scan.ids if i not in known}
    foreign = _file_rows(scan.path, lost) if lost else {}
    if foreign:
        log.warning("workbook %s holds %d row(s) the journal does not know (another journal?); they are kept",
                    scan.path, len(foreign))
    given = dict(given, **{r.cycle_id: r for r in new if hasattr(r, "record")})
    scan.header = _PartWriter(scan.path, scan.ids + [r.cycle_id for r in new], journal, given, scan.header,
                              foreign).save()
    scan.ids = scan.ids + [r.cycle_id for r in new]
    _remember(scan)


def append_rows(folder: Path, key: str, rows: list[JournalRow], settings: WorkbookSettings = WorkbookSettings(),
                journal: Journal | None = None) -> dict[Path, list[str]]:
    """Add *rows* (of one period) to that period's workbook, skipping cycle ids it already holds.

    A part that receives rows is written again whole, in streaming mode, from the journal's records of
    the rows it holds and the new ones (a part holds at most ``settings.max_rows`` rows, so this is
    bounded work and memory), and saved once, atomically. When *journal* is given, the rows are marked as
    written to their part right after its save, and rows found already present are marked too. A late
    result (``record["late"]``) whose row is in a part already gets that row rewritten in place.

    Returns
    -------
    dict
        Part path -> cycle ids added to it.

    Raises
    ------
    OSError
        A save or load failed (book open elsewhere, disk full); nothing was marked for the failing part.
    """
    folder = Path(folder)
    limit = settings.rows_per_part()
    scans = [_scan(p, journal) for p in workbook_parts(folder, key, settings.prefix)]
    last = scans[-1] if scans else None
    present: dict[Path, list[str]] = {}
    for scan in scans:
        ids = set(scan.ids)
        for r in rows:
            if r.cycle_id in ids:
                present.setdefault(scan.path, []).append(r.cycle_id)
    versions = {r.cycle_id: r.journaled_at for r in rows}
    # A late result amends a row that may be in a book already: its row there is rewritten.
    amended = {r.cycle_id: r for r in rows if _is_late(r)}
    held = {i for ids in present.values() for i in ids}
    todo = [r for r in rows if r.cycle_id not in held]
    # a row twice in *rows* (cannot happen from the journal, whose ids are unique) would be written once
    seen: set[str] = set()
    todo = [r for r in todo if not (r.cycle_id in seen or seen.add(r.cycle_id))]
    room = limit - last.n_rows if last is not None else 0
    for scan in scans:
        redo = {i: amended[i] for i in present.get(scan.path, ()) if i in amended}
        if not redo or (scan is last and todo and room > 0):
            continue                                  # the last part is written below with the new rows
        _rewrite(scan, journal, redo)
        log.info("rewrote %d late result row(s) in %s", len(redo), scan.path)
    added: dict[Path, list[str]] = {}
    book = last
    while todo:
        if book is None or book.n_rows >= limit:
            part = 1 if book is None else _part_number(folder, key, settings.prefix, book.path) + 1
            book = _PartScan(workbook_path(folder, key, part, settings.prefix), list(FIRST_COLUMNS), [])
        chunk, todo = todo[:limit - book.n_rows], todo[limit - book.n_rows:]
        redo = {i: amended[i] for i in present.get(book.path, ()) if i in amended}
        t0 = time.perf_counter()
        _rewrite(book, journal, redo, chunk)
        ids = [r.cycle_id for r in chunk]
        log.debug("saved %s with %d new row(s) (%d in all) in %.2f s", book.path, len(ids), book.n_rows,
                  time.perf_counter() - t0)
        if redo:
            log.info("rewrote %d late result row(s) in %s", len(redo), book.path)
        added[book.path] = ids
        if journal is not None:
            journal.mark_workbook(ids, book.path, versions)
    if journal is not None:
        for path, ids in present.items():
            log.info("%d row(s) were already in %s (saved before a crash, or late results); marking them",
                     len(ids), path)
            journal.mark_workbook(ids, path, versions)
    return added


def write_pending(journal: Journal, folder: Path, settings: WorkbookSettings = WorkbookSettings()) -> WorkbookReport:
    """Write every row the journal holds pending into its period's workbook under *folder*.

    A workbook that cannot be saved now (open in Excel on a share, disk full) keeps its rows pending;
    the others are still written. Never raises for such conditions: see the report.
    """
    report = WorkbookReport()
    # The pending rows without their records: the part writer reads every record from the journal a
    # hundred at a time, so a pass holds no more of them however large the backlog (PendingRow).
    pending = journal.pending_workbook_rows()
    if not pending:
        return report
    groups: dict[str, list] = {}
    for r in pending:
        groups.setdefault(period_key(r.time, settings), []).append(r)
    for key, rows in groups.items():
        try:
            added = append_rows(folder, key, rows, settings, journal)
        except (OSError, ArchiveError) as exc:
            target = workbook_path(folder, key, 1, settings.prefix)
            done = {r.cycle_id for r in rows} - {r.cycle_id for r in journal.pending_workbook_rows()}
            waiting = len(rows) - len(done)
            report.waiting += waiting
            report.errors[str(target)] = f"{type(exc).__name__}: {exc}"
            hint = ("is it open in Excel?" if isinstance(exc, PermissionError) else
                    "is the disk full?" if getattr(exc, "errno", None) == 28 else "")
            log.warning("could not save workbook rows for %s (%s: %s) %s; %d row(s) wait in the journal for "
                        "the next attempt", target, type(exc).__name__, exc, hint, waiting)
            continue
        for path, ids in added.items():
            report.written[str(path)] = report.written.get(str(path), 0) + len(ids)
        report.already_present += len(rows) - sum(len(ids) for ids in added.values())
    return report


def export_workbook(journal: Journal, since, until, path: str | Path, max_rows: int | None = None) -> list[Path]:
    """Write the journal's rows with time in ``[since, until)`` to a new workbook at *path*.

    More rows than fit one sheet continue in ``<stem>-part2.xlsx`` and so on. Each file is saved
    atomically; the journal is not changed.

    Parameters
    ----------
    journal : Journal
    since, until : str, datetime, date or None
        ISO 8601 bounds (local time when without offset); None is open.
    path : str or Path
        The ``.xlsx`` file to write (replaced when it exists).
    max_rows : int, optional
        Data rows per file; Excel's limit by default.

    Returns
    -------
    list of Path
        The files written (at least one, perhaps with only the header).
    """
    path = Path(path)
    limit = WorkbookSettings(max_rows=max_rows).rows_per_part()
    rows = journal.rows(since, until)
    total = len(rows)
    out = []
    part = 1
    while True:
        target = path if part == 1 else path.with_name(f"{path.stem}-part{part}{path.suffix}")
        chunk, rows = rows[:limit], rows[limit:]
        _PartWriter(target, [r.cycle_id for r in chunk], None, {r.cycle_id: r for r in chunk}).save()
        out.append(target)
        if not rows:
            break
        part += 1
    log.info("exported %d row(s) to %s", total, ", ".join(str(p) for p in out))
    return out
