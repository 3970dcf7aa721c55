"""Build the analysis' kernels ahead of time for this machine (``setup-env`` runs it):

    python -m sofast_station.build_kernels

numba's ahead-of-time compiler (``numba.pycc``) turns every kernel of :mod:`.measure.kernels`, for each argument
types of :mod:`.measure.kernel_signatures`, into one extension module beside them, named by
:func:`.measure.compiled.build_digest`, with a table (``<module>.json``: the module file's size and SHA-256, and
export -> kernel and argument key) that :mod:`.measure.compiled` loads instead of numba when the module matches it.
``pycc`` compiles every export with one set of default options; here each kernel gets its own, as its JIT would
(``kernels._JIT``, ``_FMA``, ``_VECTOR_SUMS``: numpy's float semantics, the GIL released, the fused multiply-adds
and regrouped sums it was written for), for this processor ('host', as the JIT), so the two give the same bits
(tests/reanalysis/test_compiled_kernels.py).

Needs a C compiler and Python's headers (Debian: gcc, python3-dev). Takes 50 to 80 s of one core on the
2-core machine CI runs on (2026-12-07; 115-130 s while it JIT-compiled each kernel first to learn its
return type, which kernel_signatures now declares). Exits 1, saying
why, when it cannot build: the analysis then runs on numba's JIT as before, only each fresh process
starts about a second later.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

from .measure import compiled

_SCALARS = {"f8": "float64", "f4": "float32", "i8": "int64", "bool": "bool"}
_DTYPES = {"f8": "<f8", "f4": "<f4", "i8": "<i8", "i4": "<i4", "u1": "|u1", "u2": "<u2", "b1": "|b1"}


def parse_word(word: str):
    """One argument of a :data:`.measure.kernel_signatures.SIGNATURES` entry: (numba type, argument key of
    :func:`.measure.compiled.argument_key`)."""
    # lazy: numba and its AOT compiler cost ~520 ms CPU and only a build needs them
    from numba import types

    numba_types = {"f8": types.float64, "f4": types.float32, "i8": types.int64, "i4": types.int32,
                   "u1": types.uint8, "u2": types.uint16, "b1": types.boolean, "bool": types.boolean}
    if ":" not in word:
        if word not in _SCALARS:
            raise ValueError(f"unknown scalar type {word!r} (one of {', '.join(_SCALARS)})")
        return numba_types[word], _SCALARS[word]
    match = re.fullmatch(r"(\w+):([1-9])([CFA])(r?)", word)
    if match is None or match.group(1) not in _DTYPES:
        raise ValueError(f"cannot read the array type {word!r} (e.g. f8:1C, u2:2C, f8:1Cr)")
    dtype, ndim, layout, readonly = match.group(1), int(match.group(2)), match.group(3), bool(match.group(4))
    return (types.Array(numba_types[dtype], ndim, layout, readonly=readonly),
            (_DTYPES[dtype], ndim, layout, not readonly))


def parse_entry(entry: str):
    """A :data:`.measure.kernel_signatures.SIGNATURES` entry: ([(numba type, argument key)] of its arguments,
    its declared return type as a numba type: ``none`` without ``->``)."""
    # lazy: numba and its AOT compiler cost ~520 ms CPU and only a build needs them
    from numba import types

    args, arrow, returned = entry.partition("->")
    parsed = [parse_word(w) for w in args.split()]
    returned = returned.strip()
    if not arrow:
        return parsed, types.none
    words = returned[1:-1].split(",") if returned.startswith("(") and returned.endswith(")") else [returned]
    scalars = []
    for w in (w.strip() for w in words):
        if w not in _SCALARS:
            raise ValueError(f"cannot read the return type {returned!r} of {entry!r} (a scalar, one of "
                             f"{', '.join(_SCALARS)}, or a tuple of them: (i8, f8))")
        scalars.append(parse_word(w)[0])
    return parsed, (types.Tuple(scalars) if returned.startswith("(") else scalars[0])


def _compile_with_own_options(dispatchers: dict):
    """numba.pycc's per-export compile step, made to use each kernel's own JIT options, and to type each
    export as the JIT would (its return type inferred, not imposed) and check that against the one
    kernel_signatures declares: an imposed type numba would cast to, where it can, silently."""
    # lazy: numba and its AOT compiler cost ~520 ms CPU and only a build needs them
    import numba.pycc.compiler as pycc_compiler
    from numba.core.compiler import Flags

    original = pycc_compiler.compile_extra

    def compile_extra(typingctx, targetctx, func, args, return_type, flags, locals, library):
        d = dispatchers[func]
        own = Flags()
        d.targetdescr.options.parse_as_flags(own, {k: v for k, v in d.targetoptions.items() if k != "cache"})
        for name in ("no_compile", "no_cpython_wrapper", "no_cfunc_wrapper"):
            setattr(own, name, getattr(flags, name))
        result = original(typingctx, targetctx, func, args, None, own, locals=locals, library=library)
        inferred = result.signature.return_type
        if inferred != return_type:
            raise ValueError(f"kernel_signatures declares {func.__name__}({', '.join(map(str, args))}) to return "
                             f"{return_type}, but it returns {inferred}: correct its '->' there")
        return result

    return original, compile_extra


def build(out_dir: Path | None = None, log=print) -> Path:
    """Build the module for the installed sources into *out_dir* (default: beside :mod:`.measure.kernels`);
    returns its path. Builds of other digests there are removed."""
    if os.environ.get(compiled.ENV) != "jit":
        raise RuntimeError(f"build() needs numba's dispatchers: run it with {compiled.ENV}=jit "
                           "(python -m sofast_station.build_kernels sets it)")
    # lazy: numba and its AOT compiler cost ~520 ms CPU and only a build needs them
    import numba
    import numba.pycc.compiler as pycc_compiler
    from numba.pycc import CC

    # lazy: kernels.py must load after main() sets SOFAST_KERNELS=jit (build() checks it)
    from .measure import kernels
    from .measure.kernel_signatures import SIGNATURES

    out_dir = Path(out_dir or compiled.BUILD_DIR)
    name = compiled.module_name()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sofast-kernels-") as tmp:
        cc = CC(name)
        cc.output_dir = tmp
        cc.target_cpu = "host"
        dispatchers, table = {}, {}
        for kernel_name, entries in SIGNATURES.items():
            d = getattr(kernels, kernel_name, None)
            if not isinstance(d, numba.core.registry.CPUDispatcher):
                raise ValueError(f"kernel_signatures names {kernel_name!r}, which is not a kernel of kernels.py")
            dispatchers[d.py_func] = d
            for i, entry in enumerate(entries):
                parsed, return_type = parse_entry(entry)
                argtypes = tuple(t for t, _ in parsed)
                export = f"{kernel_name}__{i}"
                cc.export(export, return_type(*argtypes))(d.py_func)
                table[export] = [kernel_name, [k for _, k in parsed]]
        log(f"build_kernels: compiling {len(table)} entries of {len(SIGNATURES)} kernels into {name} ...")
        original, patched = _compile_with_own_options(dispatchers)
        pycc_compiler.compile_extra = patched
        try:
            cc.compile()
        finally:
            pycc_compiler.compile_extra = original
        built = Path(tmp) / Path(cc.output_file).name
        for old in out_dir.glob(compiled.MODULE_PREFIX + "*"):
            old.unlink()
        # The table after the module: a module without its table is never loaded (compiled._load_build).
        target = out_dir / built.name
        shutil.move(str(built), target.with_suffix(".tmp"))
        os.replace(target.with_suffix(".tmp"), target)
        # The module's size and SHA-256 go into its table: a copy cut short would kill the process that loads
        # it (SIGBUS), so compiled._load_build loads only the module the build wrote.
        record = {"file": target.name, "size": target.stat().st_size, "sha256": compiled.file_digest(target)}
        table_path = out_dir / f"{name}.json"
        table_path.with_suffix(".tmp").write_text(json.dumps({"module": record, "entries": table}, indent=0))
        os.replace(table_path.with_suffix(".tmp"), table_path)
    log(f"build_kernels: {target.name} in {time.perf_counter() - t0:.1f} s")
    return target


def _sound(out_dir: Path, name: str) -> bool:
    """Whether *out_dir* holds the build *name* as it was written (its module's size and SHA-256 those its
    table records): one cut short or damaged is built again."""
    path = compiled.module_file(out_dir, name)
    try:
        return path is not None and compiled._unsound(path, json.loads((out_dir / f"{name}.json").read_text())) is None
    except (OSError, ValueError):
        return False


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out-dir", default=None, help="where to put the module (default: beside kernels.py)")
    p.add_argument("--force", action="store_true", help="build even when a build for these sources exists")
    args = p.parse_args(argv)
    out_dir = Path(args.out_dir or compiled.BUILD_DIR)
    name = compiled.module_name()
    if not args.force and _sound(out_dir, name):
        print(f"build_kernels: {name} is up to date (--force builds it again)", file=sys.stderr)
        return 0
    os.environ[compiled.ENV] = "jit"
    if "sofast_station.measure.kernels" in sys.modules and compiled.build() is not None:
        print("build_kernels: run it in a process of its own (python -m sofast_station.build_kernels)",
              file=sys.stderr)
        return 1
    try:
        build(out_dir, log=lambda line: print(line, file=sys.stderr))
    except Exception as e:          # any failure leaves the JIT in charge; say why
        print(f"build_kernels: could not build the kernels ahead of time ({type(e).__name__}: {e}); the "
              "analysis compiles them with numba's JIT instead (each fresh process starts about a second "
              "later). A C compiler and Python's headers are needed (Debian: apt-get install gcc python3-dev).",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
