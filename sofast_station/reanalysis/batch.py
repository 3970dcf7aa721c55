"""Reprocess many data dumps: on the local cores or on a Dask cluster, resumably, with a summary.

:func:`run_batch` reprocesses every dump of a folder or glob (:func:`discover_dumps`) with the same
overrides and writes, for each dump, ``OUT/results/<dump stem>.json``: the object ``sofast-station
reprocess --json`` prints (``"status": "ok"``), or ``{"dump", "status": "error", "error", ...}`` when the
dump cannot be reprocessed (a corrupt, truncated, foreign or newer dump: the error names the file and
the problem). Then it writes ``OUT/summary.csv`` and ``OUT/summary.xlsx``, one row per dump.

Resuming and crash safety
-------------------------
A result file is written as a hidden temporary file in ``OUT/results/``, flushed, fsynced and renamed to
its final name, so a result exists under its name only when it is complete; a dump counts as finished
exactly when its result file exists and parses. Workers compute and return results; only the parent
writes them. A batch killed at any moment (``SIGKILL`` of the parent and its workers) therefore leaves
finished results and perhaps hidden temporary files (removed on the next run); running the same command
again skips every finished dump and does the rest. Failed dumps are finished too (their error is their
result); ``retry_failed`` redoes them. ``OUT/batch.json`` records the overrides: a resumed batch must ask
for the same ones, so that one folder never mixes two analyses.

Where it runs
-------------
Locally, ``workers`` spawned processes (they inherit BLAS on one thread: :func:`run_batch` sets the thread
variables that the user has not set before it starts them; a worker
that dies, for example killed by the out-of-memory killer, is replaced and its dumps retried, alone, so
that only a dump that kills its worker by itself is reported as failed). With ``scheduler`` (a Dask
scheduler address, ``tcp://host:8786``) the same work runs on that cluster through
``dask.distributed.Client(address)``: the dumps must be readable by the workers under the same absolute
paths (a shared file system), the results come back to this process, which writes them. Dask's nanny
starts its workers with ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS`` and ``OPENBLAS_NUM_THREADS`` set to 1 by
default (``distributed.nanny.pre-spawn-environ``); keep that setting for bit-exact results.
"""

from __future__ import annotations

import csv
import glob as _glob
import hashlib
import io
import json
import logging
import multiprocessing
import os
import time
import traceback
from collections import deque
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Callable, Iterable

from openpyxl import Workbook
from openpyxl.cell import WriteOnlyCell
from openpyxl.styles import Font

from .. import __version__
from ..archive._common import fault_point
from ..archive.workbook import EXCEL_MAX_ROWS, _cell_value, number_format
from ..errors import ArchiveError, StationError
from ..files import fsync_dir, is_temp_file, remove_stale_temp_files, write_file_atomic, write_json_atomic
from ..precompute import prepare_analysis_process
from ..station.worker import watch_parent
from ..times import now_iso
from ._env import single_thread_blas
from .reprocess import HEADLINE, Overrides, flatten_figures, reprocess_dump

log = logging.getLogger(__name__)

#: Sub-folder of the output folder holding one JSON result per dump.
RESULTS_DIR = "results"
#: The batch's manifest: its overrides, so that a resumed batch uses the same ones.
MANIFEST = "batch.json"
SUMMARY_CSV = "summary.csv"
SUMMARY_XLSX = "summary.xlsx"

#: A dump whose worker process dies this many times, alone, is reported as failed.
_MAX_WORKER_DEATHS = 2

#: Summary columns that come first, in this order.
FIRST_COLUMNS = ("dump", "result", "status", "error", "serial", "cycle_id", "time", "verdict", "reasons", "exact",
                 "figures_compared", "figures_different", "changed_figures")


class BatchError(ArchiveError):
    """A batch cannot run: no dumps, an output folder of another batch, or no Dask."""


# -- dumps and result names ----------------------------------------------------------------------------
def _is_dump_candidate(p: Path) -> bool:
    return p.is_file() and not p.name.startswith(".") and not is_temp_file(p)


def discover_dumps(sources: Iterable[str | Path]) -> list[Path]:
    """The dumps named by folders (searched recursively for ``*.h5``), files and glob patterns.

    Parameters
    ----------
    sources : iterable of str or Path
        Folders, files (taken as named, whatever their suffix: a file that is not a dump fails with a
        clear error in the batch), or glob patterns (``**`` matches folders recursively).

    Returns
    -------
    list of Path
        Absolute paths, each once, sorted.

    Raises
    ------
    BatchError
        When a source is neither a file, a folder nor a pattern that matches something.
    """
    found: dict[str, Path] = {}
    for source in sources:
        text = str(source)
        p = Path(text).expanduser()
        if p.is_dir():
            matches = [q for q in p.rglob("*.h5") if _is_dump_candidate(q)]
        elif p.is_file():
            matches = [p]
        elif any(ch in text for ch in "*?["):
            matches = []
            for m in _glob.glob(os.path.expanduser(text), recursive=True):
                q = Path(m)
                if q.is_dir():
                    matches.extend(r for r in q.rglob("*.h5") if _is_dump_candidate(r))
                elif _is_dump_candidate(q):
                    matches.append(q)
            if not matches:
                raise BatchError(f"the pattern {text!r} matches no file")
        else:
            raise BatchError(f"{text} does not exist (neither a dump, a folder nor a glob pattern)")
        for q in matches:
            a = q.absolute()
            found[str(a)] = a
    return [found[k] for k in sorted(found)]


def result_names(dumps: list[Path]) -> dict[Path, str]:
    """File name of each dump's result: ``<dump stem>.json``, with 8 hex digits of the path's hash added
    when two dumps share a stem (dump names carry the cycle id, so that is rare)."""
    stems: dict[str, int] = {}
    for d in dumps:
        stems[d.stem] = stems.get(d.stem, 0) + 1
    out = {}
    for d in dumps:
        stem = d.stem
        if stems[stem] > 1:
            stem = f"{stem}-{hashlib.sha1(str(d).encode()).hexdigest()[:8]}"
        out[d] = f"{stem}.json"
    return out


# -- the work of one dump (runs in a worker) -------------------------------------------------------------
def error_result(dump: str | Path, exc: BaseException, internal: bool = False) -> dict:
    """The result of a dump that could not be reprocessed; the message names the file."""
    msg = str(exc)
    if str(dump) not in msg:
        msg = f"{dump}: {msg}"
    if internal:
        msg = f"internal error ({type(exc).__name__}): {msg}"
    return {"dump": str(dump), "status": "error", "error": msg, "error_type": type(exc).__name__,
            "reprocess": {"at": now_iso(), "software_version": __version__, "pid": os.getpid()}}


def process_dump(dump: str, overrides: dict | None = None, journal: str | None = None) -> dict:
    """Reprocess one dump and return its JSON-ready result; never raises for a bad dump.

    Parameters
    ----------
    dump : str
        Absolute path of the dump.
    overrides : dict, optional
        :meth:`Overrides.to_dict` of the batch's overrides.
    journal : str, optional
        Journal to take the archived record from when the dump lost it.

    Returns
    -------
    dict
        ``ReprocessResult.to_json()``, or :func:`error_result`.
    """
    fault_point(f"reprocess:{Path(dump).name}")       # crash tests: a dump that kills its worker
    try:
        return reprocess_dump(dump, Overrides.from_dict(overrides), journal=journal).to_json()
    except StationError as exc:             # reported in the summary; the batch goes on
        log.info("%s", exc)
        return error_result(dump, exc)
    except Exception as exc:                  # a bug must not stop the batch; its traceback goes to the log
        log.error("reprocessing %s failed:\n%s", dump, traceback.format_exc())
        return error_result(dump, exc, internal=True)


# -- files ------------------------------------------------------------------------------------------------
def _write_bytes_atomic(path: Path, data: bytes) -> None:
    write_file_atomic(path, lambda fh: fh.write(data), fsync=True)
    fsync_dir(path.parent)


def read_result(path: Path) -> dict | None:
    """A finished result file's object, or None when it is missing or not a complete result."""
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(obj, dict) or obj.get("status") not in ("ok", "error") or "dump" not in obj:
        return None
    return obj


def _check_manifest(out_dir: Path, overrides: dict, journal: str | None, sources: list[str]) -> None:
    path = out_dir / MANIFEST
    if path.exists():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise BatchError(f"{path} is unreadable ({exc}); it is not a batch output folder, or it was damaged: "
                             "choose another --out") from exc
        if old.get("overrides", {}) != overrides:
            raise BatchError(f"{out_dir} holds the results of a batch with the overrides {old.get('overrides')}, "
                             f"this one asks for {overrides}: choose another --out")
        if old.get("software_version") != __version__:
            log.warning("%s was started by sofast-station %s, this is %s: results of both versions will be mixed",
                        out_dir, old.get("software_version"), __version__)
        return
    write_json_atomic(path, {"created": now_iso(), "software_version": __version__, "overrides": overrides,
                             "journal": journal, "sources": sources})


# -- the batch --------------------------------------------------------------------------------------------
@dataclass
class BatchSummary:
    """What a batch did.

    Attributes
    ----------
    out_dir : Path
    total : int
        Dumps in the batch.
    reprocessed : int
        Dumps reprocessed by this run (failures included).
    skipped : int
        Dumps already finished by an earlier run, not redone.
    failed : list of (str, str)
        (dump, error) of every dump that could not be reprocessed, from this run and earlier ones.
    exact : int
        Dumps whose archived figures were all reproduced bit for bit.
    changed : int
        Dumps with at least one figure different from the archive.
    unfinished : int
        Dumps without a result (an interrupted run).
    csv_path, xlsx_path : Path
    seconds : float
        Wall time of this run, seconds.
    """

    out_dir: Path
    total: int = 0
    reprocessed: int = 0
    skipped: int = 0
    failed: list = field(default_factory=list)
    exact: int = 0
    changed: int = 0
    no_archive: int = 0
    unfinished: int = 0
    csv_path: Path | None = None
    xlsx_path: Path | None = None
    seconds: float = 0.0

    def text(self, max_failures: int = 20) -> str:
        """A short report for the command line."""
        lines = [f"{self.total} dump(s): {self.reprocessed} reprocessed now, {self.skipped} already done"
                 + (f", {self.unfinished} not finished" if self.unfinished else "") + f" ({self.seconds:.1f} s)",
                 f"  {self.exact} reproduced the archive exactly, {self.changed} differ from it"
                 + (f", {self.no_archive} had no archived result" if self.no_archive else "")
                 + f", {len(self.failed)} failed"]
        for dump, error in self.failed[:max_failures]:
            lines.append(f"  FAILED {dump}: {error}")
        if len(self.failed) > max_failures:
            lines.append(f"  ... and {len(self.failed) - max_failures} more failures (see the summary)")
        if self.csv_path:
            lines.append(f"  summary: {self.xlsx_path} and {self.csv_path}")
        return "\n".join(lines)


Progress = Callable[[int, int, int, str], None]


def run_batch(sources: Iterable[str | Path], out_dir: str | Path, overrides=None, *, workers: int | None = None,
              scheduler: str | None = None, journal: str | Path | None = None, retry_failed: bool = False,
              progress: Progress | None = None, connect_timeout_s: float = 30.0) -> BatchSummary:
    """Reprocess every dump of *sources* into *out_dir*, resuming an earlier run of the same batch.

    Parameters
    ----------
    sources : iterable of str or Path
        Folders, dump files or glob patterns (:func:`discover_dumps`).
    out_dir : str or Path
        Output folder: ``results/``, ``batch.json``, ``summary.csv``, ``summary.xlsx``.
    overrides : Overrides or dict, optional
        Applied to every dump (:class:`~sofast_station.reanalysis.reprocess.Overrides`).
    workers : int, optional
        Local worker processes; the number of CPUs by default. Ignored with *scheduler*.
    scheduler : str, optional
        Address of a Dask scheduler: run on that cluster instead of locally.
    journal : str or Path, optional
        The station's journal, for dumps that lost their archived result.
    retry_failed : bool
        Redo dumps whose earlier result is an error.
    progress : callable, optional
        ``progress(done, total, failed, name)`` after each finished dump (and once at the start).
    connect_timeout_s : float
        How long to try to reach the Dask scheduler, seconds.

    Returns
    -------
    BatchSummary

    Raises
    ------
    BatchError
        No dumps, an output folder of a batch with other overrides, or Dask missing or unreachable.
    ConfigError
        An override names a facet or calibration file that cannot be read.
    KeyboardInterrupt
        After the summary of the finished dumps has been written.
    """
    t0 = time.perf_counter()
    if overrides is None or isinstance(overrides, dict):
        overrides = Overrides.from_dict(overrides)
    overrides.check()
    ov = overrides.to_dict()
    sources = [str(s) for s in sources]
    dumps = discover_dumps(sources)
    if not dumps:
        raise BatchError(f"no dumps (*.h5) found in {', '.join(sources)}")
    out_dir = Path(out_dir).expanduser().absolute()
    results = out_dir / RESULTS_DIR
    results.mkdir(parents=True, exist_ok=True)
    journal = None if journal is None else str(Path(journal).expanduser().absolute())
    _check_manifest(out_dir, ov, journal, sources)
    remove_stale_temp_files(results, max_age_s=24 * 3600.0)
    names = result_names(dumps)
    todo = []
    for d in dumps:
        obj = read_result(results / names[d])
        if obj is None or (retry_failed and obj["status"] == "error"):
            todo.append(d)
    summary = BatchSummary(out_dir=out_dir, total=len(dumps), skipped=len(dumps) - len(todo))
    state = {"done": summary.skipped, "failed": 0}
    log.info("batch of %d dump(s) into %s: %d already done, %d to reprocess %s", len(dumps), out_dir,
             summary.skipped, len(todo), f"on the Dask cluster {scheduler}" if scheduler else
             f"on {workers or os.cpu_count() or 1} local worker(s)")
    if progress:
        progress(state["done"], len(dumps), 0, "")

    def on_result(dump: Path, obj: dict) -> None:
        write_json_atomic(results / names[dump], obj)
        summary.reprocessed += 1
        state["done"] += 1
        if obj.get("status") != "ok":
            state["failed"] += 1
        if progress:
            progress(state["done"], len(dumps), state["failed"], dump.name)

    try:
        if todo:
            if scheduler:
                _run_dask(todo, scheduler, ov, journal, on_result, connect_timeout_s)
            else:
                _run_local(todo, max(1, int(workers or os.cpu_count() or 1)), ov, journal, on_result)
    finally:
        fsync_dir(results)
        _summarise(summary, dumps, names, results)
        summary.seconds = time.perf_counter() - t0
    return summary


def _run_local(todo: list[Path], workers: int, overrides: dict, journal: str | None,
               on_result: Callable[[Path, dict], None]) -> None:
    """Reprocess *todo* on *workers* spawned processes, replacing a pool whose worker died."""
    single_thread_blas()                         # the spawned workers load numpy with BLAS on one thread
    ctx = multiprocessing.get_context("spawn")   # no inherited threads, OpenGL or HDF5 state
    # A batch ended by SIGTERM or SIGKILL cannot stop its pool: each worker exits by itself once its parent
    # is gone, instead of waiting under PID 1 for work that never comes.
    new_pool = partial(ProcessPoolExecutor, max_workers=workers, mp_context=ctx, initializer=_worker_start,
                       initargs=(os.getpid(),))
    pending = deque(todo)
    deaths: dict[Path, int] = {}
    suspects: set[Path] = set()                  # dumps in flight when a worker died: retried alone
    pool = new_pool()
    inflight: dict = {}
    finished = 0
    try:
        while pending or inflight:
            while pending and len(inflight) < 2 * workers:
                alone = any(d in suspects for d in inflight.values())
                if alone or (pending[0] in suspects and inflight):
                    break
                d = pending.popleft()
                inflight[pool.submit(process_dump, str(d), overrides, journal)] = d
                if d in suspects:
                    break
            done, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
            broken = False
            for fut in done:
                d = inflight.pop(fut)
                try:
                    obj = fut.result()
                except BrokenProcessPool:
                    broken = True
                    _worker_died(d, deaths, suspects, pending, on_result, alone=not inflight and len(done) == 1)
                    continue
                suspects.discard(d)
                finished += 1
                on_result(d, obj)
            if broken and finished == 0 and sum(n >= _MAX_WORKER_DEATHS for n in deaths.values()) >= 2:
                raise BatchError("the worker processes die before they finish any dump (two dumps each killed "
                                 "their worker twice, alone): check that a fresh Python can import sofast_station "
                                 "(the workers are spawned) and the machine's memory")
            if broken:
                for fut, d in list(inflight.items()):    # they fail with the pool: retry them
                    fut.cancel()
                    _worker_died(d, deaths, suspects, pending, on_result, alone=False)
                inflight.clear()
                pool.shutdown(wait=False, cancel_futures=True)
                log.error("a worker process died; starting a new pool of %d", workers)
                pool = new_pool()
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def _worker_start(parent_pid: int) -> None:
    """A local batch worker's start: exit with the batch (:func:`watch_parent`), and keep the memory an
    analysis frees for the next dump's and load the compiled kernels
    (:func:`~sofast_station.precompute.prepare_analysis_process`, as the station's worker does)."""
    watch_parent(parent_pid)
    prepare_analysis_process()


def _worker_died(d: Path, deaths: dict, suspects: set, pending: deque, on_result, alone: bool) -> None:
    if alone:
        deaths[d] = deaths.get(d, 0) + 1
    if deaths.get(d, 0) >= _MAX_WORKER_DEATHS:
        suspects.discard(d)
        on_result(d, error_result(d, RuntimeError(
            f"the worker process died {deaths[d]} times while reprocessing this dump alone (killed, out of memory, "
            "or a crash in a library); it was not reprocessed"), internal=False))
        return
    suspects.add(d)
    pending.appendleft(d)


def _run_dask(todo: list[Path], scheduler: str, overrides: dict, journal: str | None,
              on_result: Callable[[Path, dict], None], timeout_s: float = 30.0) -> None:
    """Reprocess *todo* on the Dask cluster at *scheduler*; results come back here."""
    try:
        # optional: Dask is the cluster extra (batch --scheduler)
        from distributed import Client, as_completed
    except ImportError as exc:
        raise BatchError("--scheduler needs Dask: pip install 'dask[distributed]>=2024.8'") from exc
    try:
        client = Client(scheduler, set_as_default=False, timeout=f"{timeout_s}s")
    except (OSError, TimeoutError) as exc:
        raise BatchError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from exc
    try:
        keys = [f"sofast-reprocess-{hashlib.sha1(str(d).encode()).hexdigest()[:16]}-{os.getpid()}" for d in todo]
        futures = client.map(process_dump, [str(d) for d in todo], overrides=overrides, journal=journal,
                             key=keys, pure=False, retries=1)
        by_key = {k: d for k, d in zip(keys, todo)}
        for fut in as_completed(futures, loop=client.loop):
            d = by_key[fut.key]
            try:
                obj = fut.result()
            except Exception as exc:          # KilledWorker and the like: the dump is reported, the batch goes on
                obj = error_result(d, exc, internal=True)
            on_result(d, obj)
            fut.release()
    finally:
        client.close()


# -- the summary ------------------------------------------------------------------------------------------
def summary_row(obj: dict, result_name: str) -> dict:
    """One summary row of a result object: fixed columns, then every figure, then archived headline figures."""
    rep = obj.get("reprocess", {}) or {}
    diffs = obj.get("differences") or {}
    row = {"dump": obj.get("dump"), "result": result_name, "status": obj.get("status"), "error": obj.get("error"),
           "serial": obj.get("serial"), "cycle_id": obj.get("cycle_id"), "time": obj.get("time"),
           "verdict": obj.get("verdict"), "reasons": obj.get("reasons"), "exact": rep.get("exact"),
           "figures_compared": rep.get("figures_compared"), "figures_different": rep.get("figures_different"),
           "changed_figures": ", ".join(diffs) or None}
    if obj.get("status") == "ok":
        for k, v in flatten_figures(obj).items():
            if k not in row:
                row[k] = v
        archived = flatten_figures(obj.get("archived") or {})
        for k in HEADLINE:
            if k in archived:
                row[f"archived.{k}"] = archived[k]
    return row


def _cell(v):
    if isinstance(v, (list, dict)):
        return json.dumps(v, ensure_ascii=False)
    return v


def _summarise(summary: BatchSummary, dumps: list[Path], names: dict, results: Path) -> None:
    rows = []
    for d in dumps:
        obj = read_result(results / names[d])
        if obj is None:
            summary.unfinished += 1
            rows.append({"dump": str(d), "result": names[d], "status": "not finished"})
            continue
        if obj["status"] != "ok":
            summary.failed.append((str(d), obj.get("error", "")))
        else:
            exact = (obj.get("reprocess") or {}).get("exact")
            if exact is True:
                summary.exact += 1
            elif exact is False:
                summary.changed += 1
            else:
                summary.no_archive += 1
        rows.append(summary_row(obj, names[d]))
    columns = list(FIRST_COLUMNS)
    seen = set(columns)
    for r in rows:
        for k in r:
            if k not in seen:
                seen.add(k)
                columns.append(k)
    out = results.parent
    summary.csv_path = out / SUMMARY_CSV
    summary.xlsx_path = out / SUMMARY_XLSX
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow(["" if r.get(c) is None else _cell(r.get(c)) for c in columns])
    _write_bytes_atomic(summary.csv_path, buf.getvalue().encode("utf-8"))
    _write_xlsx(summary.xlsx_path, columns, rows)


def _write_xlsx(path: Path, columns: list[str], rows: list[dict]) -> list[Path]:
    """The summary workbook (write-only openpyxl), split into parts at Excel's row limit, saved atomically."""
    limit = EXCEL_MAX_ROWS - 1
    parts = [rows[i:i + limit] for i in range(0, max(len(rows), 1), limit)] or [[]]
    written = []
    for n, chunk in enumerate(parts, start=1):
        target = path if n == 1 else path.with_name(f"{path.stem}-part{n}{path.suffix}")
        wb = Workbook(write_only=True)
        ws = wb.create_sheet("reprocessed")
        ws.freeze_panes = "B2"
        header = []
        for c in columns:
            cell = WriteOnlyCell(ws, value=c)
            cell.font = Font(bold=True)
            header.append(cell)
        ws.append(header)
        for r in chunk:
            out = []
            for c in columns:
                v = _cell(r.get(c))
                cell = WriteOnlyCell(ws, value=_cell_value(v) if v is not None else None)
                fmt = number_format(c, v)
                if fmt:
                    cell.number_format = fmt
                out.append(cell)
            ws.append(out)
        buf = io.BytesIO()
        wb.save(buf)
        _write_bytes_atomic(target, buf.getvalue())
        written.append(target)
    return written
