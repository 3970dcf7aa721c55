"""The journal: an append-only SQLite record of every inspection cycle (docs/conventions.md#archives).

The station appends a facet's result record *before* it releases the robot; :meth:`Journal.append`
returns only when the row is on the disk (WAL mode, ``synchronous=FULL``), so a crash, a SIGKILL or a
power cut after the robot moved on cannot lose the row. Everything else (the Excel workbook row, the HDF5
data dump) is written later by the archiver, which reads its work from the journal:

- ``workbook_path`` is NULL until the row is in a workbook, then names that workbook;
- a dump is *not requested*, *pending* (requested, neither written nor failed), *written*
  (``dump_path``) or *failed* (``dump_error`` says why).

Appends are idempotent on the cycle id: appending the same cycle twice stores it once. A re-test of a
serial is a new cycle, with its own id, and keeps both rows. One process writes (the station with its
archiver thread); any number of processes may read.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import secrets
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path

from ..errors import ArchiveError
from ._common import fault_point
from ..files import to_json
from ..times import now_iso, utc_key

log = logging.getLogger(__name__)

#: Version of the journal's table layout (SQLite ``PRAGMA user_version``).
JOURNAL_SCHEMA = 1

_CREATE = """
CREATE TABLE IF NOT EXISTS cycles (
    seq            INTEGER PRIMARY KEY AUTOINCREMENT,
    cycle_id       TEXT    NOT NULL UNIQUE,
    serial         TEXT    NOT NULL,
    time           TEXT    NOT NULL,
    time_utc       TEXT    NOT NULL,
    verdict        TEXT,
    record         TEXT    NOT NULL,
    journaled_at   TEXT    NOT NULL,
    workbook_path  TEXT,
    workbook_at    TEXT,
    dump_requested INTEGER NOT NULL,
    dump_path      TEXT,
    dump_error     TEXT,
    dump_at        TEXT
);
CREATE INDEX IF NOT EXISTS cycles_time ON cycles (time_utc);
CREATE INDEX IF NOT EXISTS cycles_serial ON cycles (serial);
CREATE INDEX IF NOT EXISTS cycles_workbook_pending ON cycles (seq) WHERE workbook_path IS NULL;
CREATE INDEX IF NOT EXISTS cycles_dump_pending ON cycles (seq)
    WHERE dump_requested = 1 AND dump_path IS NULL AND dump_error IS NULL;
"""

_COLUMNS = ("seq, cycle_id, serial, time, verdict, record, journaled_at, workbook_path, workbook_at, "
            "dump_requested, dump_path, dump_error, dump_at")


def new_cycle_id() -> str:
    """A fresh, unique, time-ordered cycle id: UTC ``YYYYMMDDTHHMMSSffffff`` and 8 random hex digits."""
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S%f")
    return f"{stamp}-{secrets.token_hex(4)}"


@dataclass(frozen=True)
class JournalRow:
    """One journaled inspection cycle.

    Attributes
    ----------
    seq : int
        Order of the append (1, 2, ...).
    cycle_id : str
    serial : str
    time : str
        The record's ISO 8601 date and time with its UTC offset.
    verdict : str or None
    record : dict
        The result record as appended (NaN and infinities stored as null).
    journaled_at : str
        When the row was appended, ISO 8601.
    workbook_path : str or None
        The workbook that holds the row; None while the row waits for its workbook.
    workbook_at : str or None
    dump_requested : bool
    dump_path : str or None
        The written data dump.
    dump_error : str or None
        Why the dump could not be written (the dump is then *failed*, no longer pending).
    dump_at : str or None
    """

    seq: int
    cycle_id: str
    serial: str
    time: str
    verdict: str | None
    record: dict
    journaled_at: str
    workbook_path: str | None
    workbook_at: str | None
    dump_requested: bool
    dump_path: str | None
    dump_error: str | None
    dump_at: str | None

    @property
    def dump_status(self) -> str:
        """``"not requested"``, ``"pending"``, ``"written"`` or ``"failed"``."""
        if self.dump_path:
            return "written"
        if self.dump_error:
            return "failed"
        return "pending" if self.dump_requested else "not requested"

    @classmethod
    def _from_sql(cls, row: tuple) -> "JournalRow":
        (seq, cycle_id, serial, time, verdict, record, journaled_at, workbook_path, workbook_at, dump_requested,
         dump_path, dump_error, dump_at) = row
        return cls(int(seq), cycle_id, serial, time, verdict, json.loads(record), journaled_at, workbook_path,
                   workbook_at, bool(dump_requested), dump_path, dump_error, dump_at)


@dataclass(frozen=True)
class PendingRow:
    """A journal row without its record: what the archiver needs to schedule work on it.

    The archiver's passes used to read the whole record of every pending row (about 50 kB of Python
    objects each at full resolution) and hold them for the pass; with saves spaced by their CPU share, a
    backlog of a hundred rows held several MB through a long save, and each pass left the archiver's memory
    higher. The records are read where they are written, a hundred at a time.
    """

    seq: int
    cycle_id: str
    serial: str
    time: str
    journaled_at: str
    late: bool


class Journal:
    """The station's append-only journal of inspection cycles (SQLite, WAL, ``synchronous=FULL``).

    Parameters
    ----------
    path : str or Path
        The database file; its folder is created. Keep it on a local disk: SQLite's WAL mode does not
        work on network shares.
    timeout_s : float
        How long a call waits for another connection's write lock, seconds.

    Notes
    -----
    One connection is shared by the threads of this process under a lock (the station thread appends,
    the archiver thread marks). Use it as a context manager or call :meth:`close`.
    """

    def __init__(self, path: str | Path, timeout_s: float = 30.0):
        self.path = Path(path)
        self._lock = threading.RLock()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(str(self.path), timeout=timeout_s, isolation_level=None,
                                       check_same_thread=False)
        except (OSError, sqlite3.Error) as exc:
            raise ArchiveError(f"cannot open the journal {self.path}: {exc}; check the folder and its "
                               "permissions (data_dir in station.toml)") from exc
        try:
            mode = self._db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise ArchiveError(f"the journal {self.path} cannot use SQLite's WAL mode (got {mode!r}); put "
                                   "data_dir on a local disk, not a network share")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute(f"PRAGMA busy_timeout={int(timeout_s * 1000)}")
            version = self._db.execute("PRAGMA user_version").fetchone()[0]
            if version > JOURNAL_SCHEMA:
                raise ArchiveError(f"the journal {self.path} has layout version {version}, written by a newer "
                                   f"sofast-station (this one knows version {JOURNAL_SCHEMA}); upgrade")
            if version < JOURNAL_SCHEMA:
                self._db.executescript(f"BEGIN IMMEDIATE;{_CREATE}PRAGMA user_version={JOURNAL_SCHEMA};COMMIT;")
        except sqlite3.DatabaseError as exc:
            self._db.close()
            raise ArchiveError(f"the journal {self.path} is not a usable SQLite database ({exc}); move it aside "
                               "and restart (its rows are lost unless the file can be repaired)") from exc
        except ArchiveError:
            self._db.close()
            raise

    # -- life cycle ---------------------------------------------------------------------------------
    def close(self) -> None:
        """Close the connection (idempotent)."""
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _conn(self) -> sqlite3.Connection:
        if self._db is None:
            raise ArchiveError(f"the journal {self.path} is closed")
        return self._db

    def _error(self, what: str, exc: Exception) -> ArchiveError:
        return ArchiveError(f"journal {self.path}: {what} failed: {exc}")

    # -- writing ------------------------------------------------------------------------------------
    def append(self, cycle_id: str, record: dict, dump_requested: bool = False) -> bool:
        """Journal one inspection cycle; durable on the disk when this returns.

        Parameters
        ----------
        cycle_id : str
            Unique id of the cycle (:func:`new_cycle_id`). Appending an id that is already journaled
            does nothing.
        record : dict
            The facet's result record; must hold ``serial`` and ``time`` (ISO 8601 with UTC offset).
        dump_requested : bool
            Whether the archiver must write an HDF5 data dump for this cycle (from its spool).

        Returns
        -------
        bool
            True when the row was added, False when the cycle id was already in the journal.

        Raises
        ------
        ArchiveError
            When the record lacks serial or time, or the database cannot be written.
        """
        if not cycle_id or not isinstance(cycle_id, str):
            raise ArchiveError(f"journal {self.path}: a cycle id must be a non-empty string, got {cycle_id!r}")
        for key in ("serial", "time"):
            if key not in record:
                raise ArchiveError(f"journal {self.path}: the record of cycle {cycle_id} has no {key!r}")
        try:
            time_utc = utc_key(record["time"])
        except ValueError:
            raise ArchiveError(f"journal {self.path}: cycle {cycle_id} has time {record['time']!r}, not ISO 8601")
        text = self._record_json(cycle_id, record)
        with self._lock:
            db = self._conn()
            try:
                db.execute("BEGIN IMMEDIATE")
                cur = db.execute(
                    "INSERT INTO cycles (cycle_id, serial, time, time_utc, verdict, record, journaled_at, "
                    "dump_requested) VALUES (?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (cycle_id) DO NOTHING",
                    (cycle_id, str(record["serial"]), str(record["time"]), time_utc, record.get("verdict"), text,
                     now_iso(), int(bool(dump_requested))))
                added = cur.rowcount == 1
                fault_point("journal-append")
                db.execute("COMMIT")
            except sqlite3.Error as exc:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise self._error(f"appending cycle {cycle_id}", exc) from exc
        if added:
            log.debug("journaled cycle %s (serial %s)", cycle_id, record["serial"])
        else:
            log.info("cycle %s is already in the journal; the second append was ignored", cycle_id)
        return added

    def _record_json(self, cycle_id: str, record: dict) -> str:
        """*record* as the journal stores it (JSON text); ArchiveError naming the cycle if it cannot be."""
        try:
            return to_json(record)
        except (TypeError, ValueError) as exc:
            raise ArchiveError(f"journal {self.path}: the record of cycle {cycle_id} cannot be stored as JSON: "
                               f"{exc}") from exc

    def amend(self, cycle_id: str, record: dict, dump_requested: bool = False) -> bool:
        """Replace the record of a journaled cycle (a late result); its workbook row is rewritten.

        The watchdog journals "fault: timeout" when a cycle misses its deadline; when the analysis then
        finishes within the grace period its figures replace that record, so the facet keeps one row.
        The record should carry ``"late": True`` (the workbook writer rewrites rows of late records).

        Returns
        -------
        bool
            True when the row was amended; False when the cycle is not journaled.
        """
        text = self._record_json(cycle_id, record)
        with self._lock:
            db = self._conn()
            try:
                db.execute("BEGIN IMMEDIATE")
                # journaled_at changes, so an archiver that read the old record does not mark the new one
                cur = db.execute("UPDATE cycles SET record = ?, verdict = ?, dump_requested = ?, journaled_at = ?, "
                                 "workbook_path = NULL, workbook_at = NULL WHERE cycle_id = ?",
                                 (text, record.get("verdict"), int(bool(dump_requested)), now_iso(), cycle_id))
                db.execute("COMMIT")
            except sqlite3.Error as exc:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise self._error(f"amending cycle {cycle_id}", exc) from exc
        return cur.rowcount == 1

    def mark_workbook(self, cycle_ids, workbook_path: str | Path, versions: dict | None = None) -> int:
        """Record that these cycles' rows are in *workbook_path*.

        Parameters
        ----------
        cycle_ids : iterable of str
        workbook_path : str or Path
            The workbook (part) file that now holds the rows.
        versions : dict, optional
            Cycle id -> ``journaled_at`` of the row as written; a row amended since (a late result) is
            not marked, so that its new record reaches the workbook too.

        Returns
        -------
        int
            Number of rows updated.
        """
        ids = list(cycle_ids)
        if not ids:
            return 0
        stamp = now_iso()
        with self._lock:
            db = self._conn()
            try:
                db.execute("BEGIN IMMEDIATE")
                n = 0
                if versions is not None:
                    for cid in ids:
                        cur = db.execute("UPDATE cycles SET workbook_path = ?, workbook_at = ? WHERE cycle_id = ? "
                                         "AND journaled_at = ?", (str(workbook_path), stamp, cid, versions.get(cid)))
                        n += cur.rowcount
                for i in range(0, len(ids), 500) if versions is None else ():
                    chunk = ids[i:i + 500]
                    cur = db.execute(f"UPDATE cycles SET workbook_path = ?, workbook_at = ? WHERE cycle_id IN "
                                     f"({','.join('?' * len(chunk))})", (str(workbook_path), stamp, *chunk))
                    n += cur.rowcount
                db.execute("COMMIT")
            except sqlite3.Error as exc:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise self._error("marking workbook rows", exc) from exc
        return n

    def mark_dump(self, cycle_id: str, path: str | Path | None, error: str | None = None) -> None:
        """Record a cycle's dump as written (*path*), failed (*path* None, *error* says why), or, with
        neither, pending again."""
        with self._lock:
            db = self._conn()
            try:
                db.execute("BEGIN IMMEDIATE")
                cur = db.execute("UPDATE cycles SET dump_path = ?, dump_error = ?, dump_at = ? WHERE cycle_id = ?",
                                 (None if path is None else str(path), None if path is not None else error,
                                  now_iso() if (path is not None or error) else None, cycle_id))
                db.execute("COMMIT")
            except sqlite3.Error as exc:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise self._error(f"marking the dump of cycle {cycle_id}", exc) from exc
        if cur.rowcount != 1:
            raise ArchiveError(f"journal {self.path}: no cycle {cycle_id!r} to mark the dump of")

    # -- reading ------------------------------------------------------------------------------------
    def _select(self, where: str = "", params: tuple = (), order: str = "seq",
                limit: int | None = None) -> list[JournalRow]:
        tail = f" LIMIT {int(limit)}" if limit else ""
        with self._lock:
            try:
                rows = self._conn().execute(f"SELECT {_COLUMNS} FROM cycles {where} ORDER BY {order}{tail}",
                                            params).fetchall()
            except sqlite3.Error as exc:
                raise self._error("reading", exc) from exc
        return [JournalRow._from_sql(r) for r in rows]

    def get(self, cycle_id: str) -> JournalRow | None:
        """The row of *cycle_id*, or None."""
        rows = self._select("WHERE cycle_id = ?", (cycle_id,))
        return rows[0] if rows else None

    def pending_workbook(self, limit: int | None = None) -> list[JournalRow]:
        """Rows not yet in a workbook, in journal order (at most *limit* of them)."""
        return self._select("WHERE workbook_path IS NULL", limit=limit)

    def pending_dumps(self) -> list[JournalRow]:
        """Rows whose dump is requested and neither written nor failed, in journal order."""
        return self._select("WHERE dump_requested = 1 AND dump_path IS NULL AND dump_error IS NULL")

    def _select_pending(self, where: str, limit: int | None = None) -> list[PendingRow]:
        tail = f" LIMIT {int(limit)}" if limit else ""
        sql = (f"SELECT seq, cycle_id, serial, time, journaled_at, json_extract(record, '$.late') FROM cycles "
               f"{where} ORDER BY seq{tail}")
        with self._lock:
            try:
                rows = self._conn().execute(sql).fetchall()
            except sqlite3.Error as exc:
                raise self._error("reading", exc) from exc
        return [PendingRow(int(q), c, s, t, j, bool(late)) for q, c, s, t, j, late in rows]

    def pending_workbook_rows(self, limit: int | None = None) -> list[PendingRow]:
        """:meth:`pending_workbook` without the records (the archiver's schedule)."""
        return self._select_pending("WHERE workbook_path IS NULL", limit)

    def pending_dump_rows(self) -> list[PendingRow]:
        """:meth:`pending_dumps` without the records (the archiver's schedule)."""
        return self._select_pending("WHERE dump_requested = 1 AND dump_path IS NULL AND dump_error IS NULL")

    def rows_in_workbook(self, workbook_path: str | Path) -> list[JournalRow]:
        """Rows recorded as written to *workbook_path*, in journal order."""
        return self._select("WHERE workbook_path = ?", (str(workbook_path),))

    def ids_in_workbook(self, workbook_path: str | Path) -> list[str]:
        """Cycle ids of the rows recorded as written to *workbook_path*, in journal order."""
        with self._lock:
            try:
                rows = self._conn().execute("SELECT cycle_id FROM cycles WHERE workbook_path = ? ORDER BY seq",
                                            (str(workbook_path),)).fetchall()
            except sqlite3.Error as exc:
                raise self._error("reading", exc) from exc
        return [r[0] for r in rows]

    def rows_by_ids(self, cycle_ids) -> dict[str, JournalRow]:
        """Cycle id -> row, for those of *cycle_ids* that are journaled (a few hundred at a time is best)."""
        ids = list(cycle_ids)
        out: dict[str, JournalRow] = {}
        for i in range(0, len(ids), 500):
            chunk = ids[i:i + 500]
            for row in self._select(f"WHERE cycle_id IN ({','.join('?' * len(chunk))})", tuple(chunk)):
                out[row.cycle_id] = row
        return out

    def known_ids(self, cycle_ids) -> set[str]:
        """Those of *cycle_ids* that are journaled."""
        ids = list(cycle_ids)
        out: set[str] = set()
        with self._lock:
            for i in range(0, len(ids), 500):
                chunk = ids[i:i + 500]
                try:
                    out.update(r[0] for r in self._conn().execute(
                        f"SELECT cycle_id FROM cycles WHERE cycle_id IN ({','.join('?' * len(chunk))})", chunk))
                except sqlite3.Error as exc:
                    raise self._error("reading", exc) from exc
        return out

    def rows(self, since=None, until=None, serial: str | None = None) -> list[JournalRow]:
        """Rows whose record time lies in ``[since, until)``, in time order.

        Parameters
        ----------
        since, until : str, datetime or date, optional
            ISO 8601 bounds; a bound without a UTC offset is local time; None is open.
        serial : str, optional
            Only this facet's rows (all its re-tests).
        """
        clauses, params = [], []
        if since is not None:
            clauses.append("time_utc >= ?")
            params.append(utc_key(since))
        if until is not None:
            clauses.append("time_utc < ?")
            params.append(utc_key(until))
        if serial is not None:
            clauses.append("serial = ?")
            params.append(serial)
        where = ("WHERE " + " AND ".join(clauses)) if clauses else ""
        return self._select(where, tuple(params), order="time_utc, seq")

    def recent(self, n: int) -> list[JournalRow]:
        """The newest *n* rows (by record time), oldest first: without reading a months-long journal whole."""
        return list(reversed(self._select(order="time_utc DESC, seq DESC", limit=max(int(n), 1))))

    def count(self) -> int:
        """Number of journaled cycles."""
        with self._lock:
            return int(self._conn().execute("SELECT COUNT(*) FROM cycles").fetchone()[0])

    def integrity_ok(self) -> bool:
        """SQLite's own consistency check of the database file."""
        with self._lock:
            return self._conn().execute("PRAGMA integrity_check").fetchone()[0] == "ok"

