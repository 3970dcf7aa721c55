"""The analysis' kernels compiled ahead of time, or by numba's JIT when no such build is installed.

numba compiles :mod:`.kernels` once and caches the machine code on disk, but every fresh process still
imports numba and initialises its compiler to load that code (0.8 to 1.2 s on the machines of
docs/performance.md): more than a whole ``reprocess`` of a dump takes otherwise. ``setup-env`` therefore
also builds the kernels into an extension module with numba's ahead-of-time compiler
(:mod:`sofast_station.build_kernels`): the same source, each kernel with its own options (fused
multiply-adds, the regrouped sums, numpy's float semantics, the GIL released) for this machine's
processor, one entry per argument types the analysis calls it with. Importing it takes a millisecond and
loads no numba. A wrong argument type would crash such an entry (it does not check types as numba's JIT
does), so every call is keyed on its arguments' exact types first (:func:`argument_key`).

The module's name carries a digest of what its code depends on (:func:`build_digest`: the kernels'
source, the list of argument types, the versions of Python, numpy and numba, the processor), so a build
made before an update is never loaded; a kernel called with argument types the build has no entry for
(:func:`argument_key`) is compiled by numba's JIT on first use, as without a build. ``SOFAST_KERNELS=jit``
ignores the build (the tests compare the two, bit for bit); any other value but ``auto`` is refused.

A build is loaded only when it is sound: its table records the module file's size and SHA-256, and a module
that does not match them (a copy cut short, which would kill the process with SIGBUS as it loads) or a table
naming entries the module lacks is left alone, with a warning saying what to do, and numba's JIT runs the
kernels instead.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import logging
import os
import platform
import sys
import threading
import types
from pathlib import Path

import numpy as np

from ..errors import ConfigError

log = logging.getLogger(__name__)

#: The environment variable that turns the ahead-of-time build off ("jit").
ENV = "SOFAST_KERNELS"
#: Its values: "auto" (the default, also when unset or empty: the build when there is a sound one, else numba's
#: JIT) and "jit" (numba's JIT always).
MODES = ("auto", "jit")
#: Prefix of the built module's name (then the digest).
MODULE_PREFIX = "_kernels_aot_"
#: Where the build is looked for (and ``build_kernels`` puts it): beside the kernels, as a module of this package.
BUILD_DIR = Path(__file__).resolve().parent

_lock = threading.Lock()
_state: dict = {}            # "build": the loaded table (or None); "jit": {kernel name: dispatcher}
_registry: list = []         # every Kernel made while a build is loaded, in source order


def installed_version(distribution: str) -> str:
    """The version of an installed distribution, read from its ``*.dist-info`` folder beside the package
    (a millisecond; ``importlib.metadata`` scans every path entry, 40 ms) without importing it."""
    spec = importlib.util.find_spec(distribution)
    if spec is not None and spec.origin:
        for info in Path(spec.origin).resolve().parent.parent.glob(f"{distribution}-*.dist-info"):
            return info.name[len(distribution) + 1:-len(".dist-info")]
    # lazy: ~20 ms CPU (+53 modules), only when no dist-info is beside the package
    from importlib import metadata

    return metadata.version(distribution)


def _processor() -> str:
    """What the machine code is built for: the processor's model and feature flags (Linux) or its name."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.machine() + platform.processor()
    keys = ("vendor_id", "model name", "flags")
    lines = {line.split(":", 1)[0].strip(): line.split(":", 1)[1].strip()
             for line in text.splitlines()[:40] if ":" in line}
    return platform.machine() + "|" + "|".join(lines.get(k, "") for k in keys)


def build_digest() -> str:
    """16 hex digits of everything the built machine code depends on; part of the module's name."""
    h = hashlib.sha256()
    for name in ("kernels.py", "kernel_signatures.py"):
        h.update((BUILD_DIR / name).read_bytes())
    h.update(json.dumps([sys.version, np.__version__, installed_version("numba"), _processor()]).encode())
    return h.hexdigest()[:16]


def module_name() -> str:
    """The built module's name for the installed sources and libraries."""
    return MODULE_PREFIX + build_digest()


def argument_key(args: tuple) -> tuple | None:
    """The types numba would give *args*, as the build's table keys them; None for a type it has no
    key for. An array: (dtype, ndim, 'C' / 'F' / 'A', writeable); a scalar: its numpy type's name
    (Python's bool, int, float as numba types them: boolean, int64, float64)."""
    key = []
    for a in args:
        if isinstance(a, np.ndarray):
            f = a.flags
            if not f.aligned:
                return None
            layout = "C" if f.c_contiguous else "F" if f.f_contiguous else "A"
            key.append((a.dtype.str, a.ndim, layout, bool(f.writeable)))
        elif isinstance(a, (bool, np.bool_)):
            key.append("bool")
        elif isinstance(a, int) and not isinstance(a, np.integer):
            if not -(1 << 63) <= a < (1 << 63):
                return None
            key.append("int64")
        elif isinstance(a, float) and not isinstance(a, np.floating):
            key.append("float64")
        elif isinstance(a, (np.integer, np.floating)):
            key.append(a.dtype.name)
        else:
            return None
    return tuple(key)


def quick_key(args: tuple) -> tuple | None:
    """What :func:`argument_key` depends on, read without building it: an array (exactly an ndarray) as its
    dtype, ndim and flag bits (alignment, layout and writability among them), Python's bool and float as
    their type, a Python int in int64's range as int; None for anything else (a numpy scalar, an array
    subclass, a larger int), which :func:`argument_key` keys. Equal quick keys have equal argument keys, so
    a :class:`Kernel` keeps its entry per quick key: a third of the time (6 against 16 us for the 16
    arrays of :func:`~.kernels.reflect`, which the uncertainty's reruns call 120 times per capture)."""
    key = []
    for a in args:
        t = type(a)
        if t is np.ndarray:
            key.append((a.dtype, a.ndim, a.flags.num))
        elif t is float or t is bool:
            key.append(t)
        elif t is int and -(1 << 63) <= a < (1 << 63):
            key.append(t)
        else:
            return None
    return tuple(key)


def kernel_mode() -> str:
    """``SOFAST_KERNELS`` as one of :data:`MODES` ("auto" when unset or empty).

    Raises
    ------
    ConfigError
        Any other value (a misspelt "jit" would otherwise pass unnoticed), naming the values allowed.
    """
    value = os.environ.get(ENV, "").strip().lower() or "auto"
    if value not in MODES:
        raise ConfigError(f"{ENV}={os.environ[ENV]!r} is not a kernel mode: use {ENV}=jit (numba's JIT) or "
                          f"{ENV}=auto (the build setup-env made, else the JIT), or leave it unset")
    return value


def module_file(folder: Path, name: str) -> Path | None:
    """The extension module *name* in *folder* (any of this Python's extension suffixes), or None."""
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        if (folder / f"{name}{suffix}").is_file():
            return folder / f"{name}{suffix}"
    return None


def file_digest(path: Path) -> str:
    """SHA-256 of a file, hex (a millisecond for the build's megabyte)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


_REBUILD = (f"run ./setup-env to rebuild it (or set {ENV}=jit to use numba's JIT without this warning); numba "
            "compiles the kernels meanwhile, so each fresh process starts about a second later")


def _unsound(path: Path, table: dict) -> str | None:
    """Why the module file *path* is not the one its build recorded in *table* (None: it is)."""
    recorded = table.get("module") if isinstance(table, dict) else None
    if not isinstance(recorded, dict) or not isinstance(table.get("entries"), dict):
        return "its table records no size and checksum of the module (a build of an older setup-env)"
    size = path.stat().st_size
    if size != recorded.get("size"):
        cut = "cut short: " if isinstance(recorded.get("size"), int) and size < recorded["size"] else ""
        return f"{cut}{size} bytes, the build wrote {recorded.get('size')} (loading it could crash the process)"
    if file_digest(path) != recorded.get("sha256"):
        return "damaged: its SHA-256 is not the one the build recorded (loading it could crash the process)"
    return None


def _load_build(folder: Path | None = None) -> dict | None:
    """{kernel name: {argument key: compiled function}} of the build for these sources in *folder* (default
    :data:`BUILD_DIR`), or None: no build, ``SOFAST_KERNELS=jit``, or a build that is not sound (a warning
    says which and what to do).

    Raises
    ------
    ConfigError
        ``SOFAST_KERNELS`` is neither unset, "auto" nor "jit".
    """
    if kernel_mode() == "jit":
        return None
    folder = Path(folder or BUILD_DIR)
    name = module_name()
    table_path = folder / f"{name}.json"
    path = module_file(folder, name)
    if path is None or not table_path.exists():
        return None
    try:
        table = json.loads(table_path.read_text())
        why = _unsound(path, table)
    except (OSError, ValueError) as e:
        why = f"its table {table_path.name} cannot be read ({e})"
    if why is not None:
        log.warning("the kernels' ahead-of-time build %s is not loaded: %s; %s", path, why, _REBUILD)
        return None
    try:
        spec = importlib.util.spec_from_file_location(f"{__package__}.{name}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except (ImportError, OSError) as e:
        log.warning("the kernels' ahead-of-time build %s could not be loaded (%s); %s", path, e, _REBUILD)
        return None
    entries = table["entries"]
    try:
        missing = sorted(export for export in entries if not callable(getattr(module, export, None)))
        if missing:
            raise ValueError(f"its table names {len(missing)} entries the module lacks ({', '.join(missing[:3])}"
                             f"{', ...' if len(missing) > 3 else ''})")
        built: dict = {}
        for export, (kernel, key) in entries.items():
            built.setdefault(kernel, {})[_as_key(key)] = getattr(module, export)
    except (TypeError, ValueError) as e:
        log.warning("the kernels' ahead-of-time build %s is not loaded: %s; %s", path, e, _REBUILD)
        return None
    return built


def _as_key(key: list) -> tuple:
    return tuple(tuple(k) if isinstance(k, list) else k for k in key)


def build() -> dict | None:
    """The loaded build's table (loaded once per process), or None without one."""
    with _lock:
        if "build" not in _state:
            _state["build"] = _load_build()
        return _state["build"]


class Kernel:
    """A kernel of :mod:`.kernels` while a build is loaded: called with argument types the build has an
    entry for, it runs that entry; otherwise numba's JIT compiles it (:func:`_jit`)."""

    def __init__(self, py_func, options: dict, entries: dict):
        self.py_func = py_func
        self.options = options
        self.entries = entries
        self.known: dict = {}       # quick_key -> the entry argument_key chose for it
        self.__name__ = py_func.__name__
        self.__doc__ = py_func.__doc__
        self.__wrapped__ = py_func

    def __call__(self, *args):
        quick = quick_key(args)
        fn = self.known.get(quick) if quick is not None else None
        if fn is None:
            fn = self.entries.get(argument_key(args))
            if fn is None:
                return _jit(self.__name__)(*args)
            if quick is not None:
                self.known[quick] = fn
        return fn(*args)

    def __repr__(self) -> str:
        return f"<kernel {self.__name__} ({len(self.entries)} compiled ahead of time)>"


def _jit(name: str):
    """numba's JIT dispatcher of kernel *name*. The first call makes one for every kernel, from copies of
    their functions whose module globals name the dispatchers (a kernel calls others by name, which numba
    must see as its own functions, not as :class:`Kernel`)."""
    with _lock:
        if "jit" not in _state:
            # lazy: numba, ~180 ms CPU to import and ~1 s to start; only numba's JIT (no build) needs it
            import numba

            # a warning, not a note: it costs this process about a second (numba's start), or 10-20 s to compile
            log.warning("kernel %s was called with argument types the ahead-of-time build has no entry for: numba "
                        "loads (or compiles) the kernels, about a second, in this process; if this recurs, add "
                        "the types to measure/kernel_signatures.py and run ./setup-env", name)
            namespace = dict(sys.modules[_registry[0].py_func.__module__].__dict__)
            dispatchers = {}
            for k in _registry:
                f = k.py_func
                copy = types.FunctionType(f.__code__, namespace, f.__name__, f.__defaults__, f.__closure__)
                copy.__qualname__, copy.__module__, copy.__doc__ = f.__qualname__, f.__module__, f.__doc__
                dispatchers[k.__name__] = namespace[k.__name__] = numba.njit(**k.options)(copy)
            _state["jit"] = dispatchers
        return _state["jit"][name]


def kernel(**options):
    """The decorator of :mod:`.kernels`: ``numba.njit(**options)`` without a build (as before builds
    existed), else a :class:`Kernel` holding the build's entries for the function."""

    def wrap(fn):
        table = build()
        if table is None:
            # lazy: numba, ~180 ms CPU to import and ~1 s to start; only numba's JIT (no build) needs it
            import numba

            return numba.njit(**options)(fn)
        k = Kernel(fn, options, table.get(fn.__name__, {}))
        _registry.append(k)
        return k

    return wrap
