"""The one registry of ``sofast-station`` commands, and what every command module shares.

:data:`COMMAND_MODULES` lists the modules that provide commands, in the order ``sofast-station --help``
shows them. Each has ``register(subparsers)``, which adds its commands (with their options and a
``func`` default: ``func(args) -> exit status``). :func:`build_parser` imports them by name when it builds
the parser, so a command module never imports ``sofast_station.cli`` or another command module: they all
import this module, which imports none of them. A new command is a ``register`` function in its program's
command module (``station/cli.py``, ``station/calibrate_cli.py``, ``reanalysis/cli.py``...) and one line here.

This module imports only the standard library, so ``--help`` and every command start fast; commands import
numpy, the analysis and the devices inside their ``func``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import re
import sys
import textwrap
from pathlib import Path

from . import __version__
from .errors import ConfigError, StationError

log = logging.getLogger("sofast_station")

#: The modules providing commands, in ``--help`` order, each with ``register(subparsers)``.
COMMAND_MODULES = (
    "sofast_station.station.cli",            # the production line: inspect, run, serve, dump-next, archive export
    "sofast_station.station.calibrate_cli",  # the morning calibration: calibrate radiometric|camera|geometry|status
    "sofast_station.reanalysis.cli",         # the process and quality engineers: reprocess, batch, report
    "sofast_station.interop.cli",            # import-opencsp
    "sofast_station.station.study_cli",      # study repeatability (the twin)
    "sofast_station.field.cli",              # field orientation | canting (the tower's camera)
)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Plain-text help: paragraphs of a description re-wrapped to the terminal, indented lines (examples)
    kept as written, and every option's default shown.

    A default is appended as ``(default: X)`` unless the help text already speaks of its default, or the
    default is ``None`` or a flag's ``False`` (then the help says what happens without the option).
    """

    def __init__(self, prog, indent_increment=2, max_help_position=30, width=None):
        width = width or min(100, max(60, _terminal_width() - 2))
        super().__init__(prog, indent_increment, max_help_position, width)

    def _fill_text(self, text, width, indent):
        blocks = []
        for block in re.split(r"\n\s*\n", textwrap.dedent(text).strip("\n")):
            out, words = [], []
            for line in block.splitlines() + [" "]:
                if line.startswith(" "):                  # an indented line (example, table): as written
                    if words:
                        out.append(textwrap.fill(" ".join(words), width, initial_indent=indent,
                                                 subsequent_indent=indent, break_on_hyphens=False))
                        words = []
                    if line.strip():
                        out.append(indent + line.rstrip())
                else:
                    words.append(line.strip())
            blocks.append("\n".join(out))
        return "\n\n".join(blocks) + "\n"

    def _split_lines(self, text, width):
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if ("default" in text.lower() or default is None or default is False or default is argparse.SUPPRESS
                or not (action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE))):
            return text
        return f"{text} (default: %(default)s)"


def _terminal_width() -> int:
    # lazy: shutil brings bz2, lzma and zlib (~3 ms CPU); importing the entry point needs none, a help text does
    import shutil

    try:
        return shutil.get_terminal_size().columns
    except (OSError, ValueError):           # pragma: no cover
        return 100


def add_command(subparsers, name: str, help: str, description: str, **kwargs) -> argparse.ArgumentParser:
    """Add one command: *help* is its line in the list of commands, *description* the paragraph(s) at the
    top of its own ``--help`` (plain text; blank lines separate paragraphs, indented lines stay as
    written)."""
    return subparsers.add_parser(name, help=help, description=description, formatter_class=HelpFormatter,
                                 **kwargs)


def default_config() -> str:
    """station.toml in the current folder, else the one beside the package (a source checkout)."""
    here = Path("station.toml")
    if here.exists():
        return str(here)
    return str(Path(__file__).resolve().parents[1] / "station.toml")


def add_config_option(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    """The ``--config`` option every station command takes."""
    parser.add_argument("--config", metavar="FILE", default=default or default_config(),
                        help="the station file (default: ./station.toml if present, else the one beside the "
                             "package)")


def positive_int(text: str) -> int:
    """argparse type: a whole number of at least 1 (``--facets 0`` or ``-3`` is a usage error, exit 2)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def lower_priority(niceness: int = 10) -> None:
    """Run this process (and the processes it starts) *niceness* steps below normal priority.

    For the commands that may run on the station computer beside ``run`` (batch, report, the web page):
    the measuring loop keeps its cores. ``SOFAST_NICE=0`` in the environment turns it off.
    """
    niceness = int(os.environ.get("SOFAST_NICE", niceness))
    if niceness <= 0 or not hasattr(os, "nice"):
        return
    try:
        current = os.nice(0)
        if current < niceness:
            os.nice(niceness - current)
            log.debug("running at niceness %d so the measuring loop is not starved", niceness)
    except OSError as exc:                   # not allowed here: run at the normal priority
        log.debug("could not lower the priority: %s", exc)


#: Environment variables that set the thread count of the BLAS/OpenMP libraries numpy may use, and of
#: OpenCV's own pool (whose idle workers wait for work by yielding the processor over and over: on two
#: cores they took a tenth of a full-resolution reprocess from the analysis' own threads).
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")


def single_thread_blas() -> bool:
    """Ask for BLAS (and OpenCV) on one thread, unless the user set a thread count explicitly (before numpy
    is loaded: the libraries read it when they load; docs/conventions.md#determinism).

    One thread gives the re-analysis its bit-exact results, and spares a one-off command the start of a
    thread pool it does not need: on a busy machine, OpenBLAS's first call (scipy's triangulation of the
    OpenCSP screen) took 0.3 to 1.2 s with its pool, half a millisecond without. OpenCV's pool gave the
    analysis nothing (its images are small) and its idle worker spun on the second core (1,400 yields of
    the processor in one reprocess): 12 % of a reprocess's wall time.

    Returns
    -------
    bool
        True when numpy was not loaded yet, so the setting takes effect in this process (it always
        takes effect in processes started afterwards).
    """
    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, "1")
    return "numpy" not in sys.modules


def check_station_file(args: argparse.Namespace) -> None:
    """Refuse a command whose station file (``--config``) is missing or not TOML before the command loads
    anything: the mistake is reported in a tenth of a second, not after numpy, OpenCV and the analysis'
    kernels have been loaded (what ``load_config`` needs). Commands without ``--config``, or whose
    ``--config`` was left unset (``report``), pass.

    Raises
    ------
    ConfigError
        Naming the file and what to do.
    """
    path = getattr(args, "config", None)
    if not isinstance(path, (str, Path)) or not str(path):
        return

    # lazy: tomllib costs ~10 ms (its patterns); the entry point (cli.py imports this module) needs none
    import tomllib

    path = Path(path).expanduser().resolve()
    # The words of files.read_toml, which load_config reads the file with (this module imports no other).
    try:
        tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"station file {path} does not exist; pass --config or run from the project "
                          "folder") from None
    except IsADirectoryError:
        raise ConfigError(f"station file {path} is a folder: pass --config with the station.toml in it") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"station file {path} is not valid TOML: {exc}") from None


def build_parser(prog: str = "sofast-station", description: str = "", epilog: str = "",
                 modules=COMMAND_MODULES) -> argparse.ArgumentParser:
    """The parser of every command of *modules* (by default all of :data:`COMMAND_MODULES`)."""
    p = argparse.ArgumentParser(prog=prog, description=description, epilog=epilog, formatter_class=HelpFormatter)
    p.add_argument("--version", action="version", version=f"sofast-station {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="log debugging detail on stderr")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", title="commands")
    for name in modules:
        importlib.import_module(name).register(sub)
    return p


def run(args: argparse.Namespace) -> int:
    """Run a parsed command: logging to stderr, a StationError is one line and exit code 2.

    Exit codes (README, "The main commands"): 0 done; 1 the command ran but part of its work failed (batch: a
    dump failed or is unfinished); 2 a user's mistake or a station error, one line saying what to do (argparse
    usage errors too); 130 interrupted (Ctrl-C). Output piped into a reader that stops early (``head``)
    ends quietly with 0.
    """
    logging.basicConfig(level=logging.DEBUG if getattr(args, "verbose", False) else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    try:
        check_station_file(args)
        return args.func(args)
    except StationError as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130
    except BrokenPipeError:
        # the reader went away (`... | head`): not an error of ours; silence the interpreter's final flush
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except OSError:
            pass
        return 0
