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
ignores the build (the tests compare the two, bit for bit).
"""

from __future__ import annotations

import hashlib
import importlib
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

log = logging.getLogger(__name__)

#: The environment variable that turns the ahead-of-time build off ("jit").
ENV = "SOFAST_KERNELS"
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


def _load_build() -> dict | None:
    """{kernel name: {argument key: compiled function}} of the build for these sources, or None."""
    if os.environ.get(ENV, "").strip().lower() == "jit":
        return None
    name = module_name()
    table_path = BUILD_DIR / f"{name}.json"
    if importlib.util.find_spec(f"{__package__}.{name}") is None or not table_path.exists():
        return None
    try:
        module = importlib.import_module(f"{__package__}.{name}")
        entries = json.loads(table_path.read_text())
    except (ImportError, OSError, ValueError) as e:
        log.warning("the kernels' ahead-of-time build %s could not be loaded (%s); numba compiles them "
                    "instead (run ./setup-env to rebuild it)", name, e)
        return None
    table: dict = {}
    for export, (kernel, key) in entries.items():
        table.setdefault(kernel, {})[_as_key(key)] = getattr(module, export)
    return table


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
        self.__name__ = py_func.__name__
        self.__doc__ = py_func.__doc__
        self.__wrapped__ = py_func

    def __call__(self, *args):
        fn = self.entries.get(argument_key(args))
        if fn is None:
            return _jit(self.__name__)(*args)
        return fn(*args)

    def __repr__(self) -> str:
        return f"<kernel {self.__name__} ({len(self.entries)} compiled ahead of time)>"


def _jit(name: str):
    """numba's JIT dispatcher of kernel *name*. The first call makes one for every kernel, from copies of
    their functions whose module globals name the dispatchers (a kernel calls others by name, which numba
    must see as its own functions, not as :class:`Kernel`)."""
    with _lock:
        if "jit" not in _state:
            import numba

            log.info("a kernel was called with argument types the ahead-of-time build has no entry for: "
                     "numba loads (or compiles) the kernels")
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
            import numba

            return numba.njit(**options)(fn)
        k = Kernel(fn, options, table.get(fn.__name__, {}))
        _registry.append(k)
        return k

    return wrap
