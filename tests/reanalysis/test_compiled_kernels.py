"""The kernels built ahead of time (sofast_station/measure/compiled.py, sofast_station/build_kernels.py; issue 32).

What must hold: a process that reprocesses a dump with the build loads no numba at all, and its figures
are the JIT's bit for bit; the build's table keys argument types as the runtime does; a call the build
has no entry for still runs (numba's JIT, the same values).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from sofast_station import build_kernels
from sofast_station.measure import compiled, kernels
from sofast_station.measure.kernel_signatures import SIGNATURES
from tests.conftest import ROOT

_REPROCESS = """
import json, sys
from sofast_station.cli import main
rc = main(["reprocess", "--json", *sys.argv[1:]])
print(json.dumps({"rc": rc, "numba": "numba" in sys.modules}))
"""


def _reprocess(dump, jit: bool, *extra) -> tuple[dict, dict]:
    env = {**os.environ, compiled.ENV: "jit" if jit else ""}
    out = subprocess.run([sys.executable, "-c", _REPROCESS, str(dump), *extra], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    return json.loads(lines[-2]), json.loads(lines[-1])


def _without_clock(record: dict) -> dict:
    """The record less what a run's clock and process set (timings, pid, time of day)."""
    record = dict(record)
    record.pop("timings_s", None)
    record["reprocess"] = {k: v for k, v in record.get("reprocess", {}).items() if k not in ("pid", "at")}
    return record


def test_setup_env_built_the_kernels_for_this_machine():
    # The README's commands run ./setup-env, which builds them (gcc and Python's headers are among its
    # Debian packages); without the build every command would start numba again (about a second).
    if os.environ.get(compiled.ENV, "").lower() == "jit":
        pytest.skip(f"{compiled.ENV}=jit: the build is switched off")
    table = compiled.build()
    assert table is not None, "no build of the kernels for these sources: run ./setup-env"
    assert isinstance(kernels._atan_into, compiled.Kernel)
    for name, entries in SIGNATURES.items():
        assert len(table[name]) == len(entries), name


def test_a_reprocess_on_the_build_loads_no_numba_and_gives_the_jits_figures_bit_for_bit(station_dumps):
    if compiled.build() is None:
        pytest.skip("no build of the kernels (test_setup_env_built_the_kernels_for_this_machine says why)")
    dump = station_dumps.good[0]
    for extra in ((), ("--focal-length", "5.4")):
        built, built_proc = _reprocess(dump, False, *extra)
        jit, jit_proc = _reprocess(dump, True, *extra)
        assert built_proc == {"rc": 0, "numba": False}
        assert jit_proc == {"rc": 0, "numba": True}
        assert _without_clock(built) == _without_clock(jit)
        assert built["focal_length_x_m"] == jit["focal_length_x_m"] and np.isfinite(built["focal_length_x_m"])


_NUMBA_FREE = """
import json, sys
from sofast_station.cli import main
rc = main(sys.argv[1:])
print(json.dumps({"rc": rc, "numba": "numba" in sys.modules}))
"""


@pytest.mark.parametrize("command", ["inspect", "import-opencsp"])
def test_inspect_and_import_opencsp_on_the_build_load_no_numba(command, small_station_toml, tmp_path):
    """Issue 46, item 8: not only reprocess; the README's first command and the OpenCSP route too."""
    if compiled.build() is None:
        pytest.skip("no build of the kernels (test_setup_env_built_the_kernels_for_this_machine says why)")
    if command == "inspect":
        argv = ["inspect", "--config", str(small_station_toml), "--noise-free", "--json"]
    else:
        argv = ["import-opencsp", "--test-data", str(ROOT / "fixtures/opencsp/test_data"), "--json"]
    out = subprocess.run([sys.executable, "-c", _NUMBA_FREE, *argv], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600, env={**os.environ, compiled.ENV: "", "SOFAST_DATA_DIR": str(tmp_path / "d")})
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {"rc": 0, "numba": False}, out.stderr[-2000:]


def _array_for(word: str) -> np.ndarray:
    """An array of the type a kernel_signatures word names (the build's key must be the runtime's)."""
    dtype, shape = word.split(":")
    ndim, layout, readonly = int(shape[0]), shape[1], shape.endswith("r")
    np_dtype = {"f8": np.float64, "f4": np.float32, "i8": np.int64, "i4": np.int32, "u1": np.uint8,
                "u2": np.uint16, "b1": np.bool_}[dtype]
    a = np.zeros((3, 4, 5)[:ndim], dtype=np_dtype)
    if layout == "F":
        a = np.asfortranarray(a)
    elif layout == "A":
        a = np.zeros((6, 8, 10)[:ndim], dtype=np_dtype)[(slice(None, None, 2),) * ndim]
    a.flags.writeable = not readonly
    return a


def test_the_builds_keys_are_the_runtimes_for_every_entry():
    scalars = {"f8": 1.5, "f4": np.float32(1.5), "i8": 3, "bool": True}
    n = 0
    for name, entries in SIGNATURES.items():
        assert hasattr(kernels, name), f"kernel_signatures names {name}, which kernels.py lacks"
        for entry in entries:
            words = entry.partition("->")[0].split()
            args = tuple(scalars[w] if ":" not in w else _array_for(w) for w in words)
            built_key = tuple(k for _, k in build_kernels.parse_entry(entry)[0])
            assert compiled.argument_key(args) == built_key, (name, entry)
            n += 1
    assert n == sum(len(v) for v in SIGNATURES.values()) > 30


def test_argument_keys_tell_apart_what_numba_compiles_apart():
    c = np.zeros((3, 4))
    assert compiled.argument_key((c,)) == (("<f8", 2, "C", True),)
    assert compiled.argument_key((np.asfortranarray(c),))[0][2] == "F"
    assert compiled.argument_key((c[:, ::2],))[0][2] == "A"
    ro = c.copy()
    ro.flags.writeable = False
    assert compiled.argument_key((ro,))[0][3] is False
    # Python's bool, int and float as numba types them; numpy scalars as their own type
    assert compiled.argument_key((True, np.bool_(False), 3, 2.0, np.float64(2.0), np.float32(2.0), np.int32(1))) \
        == ("bool", "bool", "int64", "float64", "float64", "float32", "int32")
    assert compiled.argument_key((1 << 70,)) is None
    assert compiled.argument_key(([1.0],)) is None
    with pytest.raises(ValueError, match="f8:1C"):
        build_kernels.parse_word("f8:C1")
    with pytest.raises(ValueError, match="unknown scalar"):
        build_kernels.parse_word("f16")


def _arrays_of_every_kind() -> list:
    """Arrays differing in each thing numba compiles apart: dtype (a byte-swapped one too), ndim, layout
    (C, F, neither, one element: both), writability, alignment."""
    out = []
    for dtype in (np.float64, np.dtype(">f8"), np.float32, np.int64, np.int32, np.uint8, np.uint16, np.bool_):
        for shape in ((5,), (1,), (3, 4), (1, 1), (2, 3, 4)):
            c = np.zeros(shape, dtype=dtype)
            out += [c, np.asfortranarray(c), c[(slice(None, None, 2),) * c.ndim], c.T]
    ro = np.zeros((3, 4))
    ro.flags.writeable = False
    unaligned = np.zeros(41, dtype=np.uint8)[1:].view(np.float64)
    return out + [ro, ro[:, ::2], unaligned, np.zeros(5)[:4]]


def test_equal_quick_keys_have_equal_argument_keys_and_a_kernel_keeps_the_build_entry_for_each():
    """A kernel keeps the entry it chose per quick_key (cheaper than argument_key): two calls whose quick
    keys are equal must be the same types to numba, or a second call could run an entry built for
    others (and crash). Every pair of arguments of every kind; then a kernel's kept entries are the ones
    argument_key picks."""
    values = _arrays_of_every_kind() + [True, False, 3, -(1 << 63), 2.0, np.float64(2.0), np.float32(2.0),
                                        np.int32(1), np.bool_(True), 1 << 63, [1.0], None]
    quick = [compiled.quick_key((v,)) for v in values]
    keys = [compiled.argument_key((v,)) for v in values]
    assert len({q for q in quick if q is not None}) > 100
    for q, k in zip(quick, keys):
        for q2, k2 in zip(quick, keys):
            if q is not None and q == q2:
                assert k == k2
    assert compiled.quick_key((np.float64(2.0),)) is None and compiled.quick_key((1 << 63,)) is None
    if compiled.build() is None:
        pytest.skip("no build of the kernels: nothing kept")
    x = np.linspace(-3.0, 3.0, 11)
    out = np.empty_like(x)
    k = kernels._atan_into
    k(x, out)
    k(x[:5].copy(), out[:5])
    assert k.known[compiled.quick_key((x, out))] is k.entries[compiled.argument_key((x, out))]
    assert np.array_equal(out[5:], kernels.atan(x)[5:])


def test_a_call_the_build_has_no_entry_for_runs_on_the_jit_with_the_same_values():
    if compiled.build() is None:
        pytest.skip("no build of the kernels")
    # float32 arrays: the build has atan for float64 only; the JIT compiles it for float32 (what numba
    # did for every call before the build)
    x = np.linspace(-30.0, 30.0, 1001)
    out64 = np.empty_like(x)
    kernels._atan_into(x, out64)
    x32 = x.astype(np.float32)
    out32 = np.empty_like(x32)
    kernels._atan_into(x32, out32)
    assert np.allclose(out32, np.arctan(x32), atol=2e-7)
    assert np.array_equal(out64, kernels.atan(x))
    assert np.max(np.abs(out64 - np.arctan(x))) < 1e-15
    # a kernel that only other kernels call (no entry at all)
    a = np.array([5.0, 1.0, 3.0, 2.0, 4.0])
    assert kernels._median_of(a, 0.0, False, -10.0, 10.0, np.empty(5)) == 3.0
    assert kernels._median_of(a, 3.0, True, -np.inf, np.inf, np.empty(5)) == 1.0


# -- a build that is not sound, and a mode nobody meant (issue 43) --------------------------------------------
_LOAD_FROM = """
import json, sys
from pathlib import Path
from sofast_station.measure import compiled
print(json.dumps({"loaded": compiled._load_build(Path(sys.argv[1])) is not None}))
"""


def _copy_of_the_build(tmp_path) -> tuple:
    """The installed build's module and table copied into *tmp_path* (the tests damage the copy)."""
    import shutil

    if compiled.build() is None:
        pytest.skip("no build of the kernels (test_setup_env_built_the_kernels_for_this_machine says why)")
    name = compiled.module_name()
    module = compiled.module_file(compiled.BUILD_DIR, name)
    shutil.copy(module, tmp_path / module.name)
    shutil.copy(compiled.BUILD_DIR / f"{name}.json", tmp_path / f"{name}.json")
    return tmp_path / module.name, tmp_path / f"{name}.json"


def _load_in_a_fresh_process(folder) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _LOAD_FROM, str(folder)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env={**os.environ, compiled.ENV: ""})


def test_a_build_cut_short_is_left_alone_with_what_to_do(tmp_path):
    """A module cut to half its size killed every command with SIGBUS as it loaded, without a word (issue
    43): now it is not loaded, the process goes on on numba's JIT, and the warning says what to do."""
    module, _ = _copy_of_the_build(tmp_path)
    with open(module, "r+b") as fh:
        fh.truncate(module.stat().st_size // 2)
    out = _load_in_a_fresh_process(tmp_path)
    assert out.returncode == 0, f"exit {out.returncode} (-7: SIGBUS) {out.stderr[-1500:]}"
    assert json.loads(out.stdout.splitlines()[-1]) == {"loaded": False}
    assert "cut short" in out.stderr and "./setup-env" in out.stderr and f"{compiled.ENV}=jit" in out.stderr


def test_a_table_naming_entries_the_module_lacks_is_left_alone_with_what_to_do(tmp_path):
    """It ended in an AttributeError traceback (compiled._load_build); now a warning naming the entry."""
    _, table_path = _copy_of_the_build(tmp_path)
    table = json.loads(table_path.read_text())
    entries = table["entries"] if "entries" in table else table
    entries["_atan_into__99"] = entries["_atan_into__0"]
    table_path.write_text(json.dumps(table))
    out = _load_in_a_fresh_process(tmp_path)
    assert out.returncode == 0, out.stderr[-1500:]
    assert "Traceback" not in out.stderr
    assert json.loads(out.stdout.splitlines()[-1]) == {"loaded": False}
    assert "_atan_into__99" in out.stderr and "./setup-env" in out.stderr


def test_the_build_as_written_is_loaded_from_its_folder(tmp_path):
    """The same copy, undamaged, is loaded (the checks above refuse the damage, not the copy)."""
    _copy_of_the_build(tmp_path)
    out = _load_in_a_fresh_process(tmp_path)
    assert json.loads(out.stdout.splitlines()[-1]) == {"loaded": True}, out.stderr[-1500:]


def test_a_kernel_mode_nobody_meant_is_refused_in_one_line(small_station_toml):
    """SOFAST_KERNELS=garbage was ignored (the build used as if unset); now every command that loads a station
    refuses it in one line naming the values allowed, exit 2."""
    out = subprocess.run([sys.executable, "-m", "sofast_station", "calibrate", "status", "--config",
                          str(small_station_toml)], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**os.environ, compiled.ENV: "garbage"})
    assert out.returncode == 2, out.stderr[-1500:]
    assert "Traceback" not in out.stderr
    (line,) = [line for line in out.stderr.splitlines() if "ERROR" in line]
    assert "SOFAST_KERNELS='garbage'" in line and "SOFAST_KERNELS=jit" in line and "SOFAST_KERNELS=auto" in line
    for value in ("", "auto", " JIT "):
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv(compiled.ENV, value)
            assert compiled.kernel_mode() == (value.strip().lower() or "auto")


@pytest.mark.filterwarnings("ignore::PendingDeprecationWarning")      # numba.pycc's own notice
def test_a_declared_return_type_is_read_and_a_wrong_one_stops_the_build(tmp_path):
    """kernel_signatures declares each entry's return type (the build no longer JIT-compiles a kernel to learn
    it); the build types each export as the JIT does and stops, naming the entry, where the two differ, rather
    than let numba cast the kernel's value to the declared type."""
    import numba
    import numba.pycc.compiler as pycc_compiler
    from numba import types
    from numba.pycc import CC

    args, returned = build_kernels.parse_entry("f8:1C i8 -> (i8, f8)")
    assert [t for t, _ in args] == [types.Array(types.float64, 1, "C"), types.int64]
    assert returned == types.Tuple((types.int64, types.float64))
    assert build_kernels.parse_entry("u1:2Cr")[1] == types.none
    with pytest.raises(ValueError, match="return type"):
        build_kernels.parse_entry("f8:1C -> f8:1C")

    @numba.njit
    def length(x):
        return x.shape[0]

    parsed, wrong = build_kernels.parse_entry("f8:1C -> f8")        # it returns an int64
    cc = CC("_kernels_wrong_return")
    cc.output_dir = str(tmp_path)
    cc.export("length", wrong(*[t for t, _ in parsed]))(length.py_func)
    original, patched = build_kernels._compile_with_own_options({length.py_func: length})
    pycc_compiler.compile_extra = patched
    try:
        with pytest.raises(ValueError, match=r"declares length\(array\(float64, 1d, C\)\) to return float64, but it "
                                             r"returns int64"):
            cc.compile()
    finally:
        pycc_compiler.compile_extra = original
