"""numba kernels compiled ahead of time, with numba's JIT as the fallback.

A process that calls a numba kernel pays for ``import numba`` (0.15-0.2 s with the SciPy it
pulls in) and for numba's first call (0.3-0.5 s to load its target and the cached kernels),
even when every kernel is cached on disk: the whole of ``octofactor map`` on a tiny graph took
0.8 s, of which 0.05 s was the work (issue 15). The kernels of a module such as
``mapping._kernels`` are therefore also compiled into a plain CPython extension module
(``numba.pycc``) when the project is set up (``make setup``, which ``make test`` and ``make
demo`` run; by hand ``python -m estimation.aot build``). Loading it needs neither numba nor
LLVM.

:func:`kernels` returns the namespace the Python code calls the kernels through. Each call
looks up the exact numba types of its arguments (dtype, dimensions, layout, read-only, as
``numba.typeof`` gives them) in the table of signatures compiled ahead of time
(``<module>.aot.json`` beside the kernels' source): a match calls the compiled function, any
other call goes to the ``@njit`` dispatcher, which compiles or loads it as before. Results
are the same either way: the same numba front end compiles both, from the same source, with
the same flags (no fastmath, Python error model; the GIL is released as with ``nogil``).

The compiled module's name carries a hash of the kernels' source, of the signature table, of
:data:`ABI`, of numpy's version and of the CPU (it is compiled for the host's instruction
set), so an edited kernel or another machine silently falls back to the JIT instead of running
stale code.
``OCTOFACTOR_JIT=1`` in the environment switches the compiled modules off.
"""
from __future__ import annotations

import hashlib
import importlib
import importlib.util
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: kernel modules compiled ahead of time by ``python -m estimation.aot build``
MODULES = ("mapping._kernels", "estimation.registration._kernels")
_JIT_ONLY = os.environ.get("OCTOFACTOR_JIT", "") not in ("", "0")
_RECORD = os.environ.get("OCTOFACTOR_AOT_RECORD") or None  # "1": add calls to the tables
_recorded: dict[str, dict[str, set]] = {}


def arg_key(value) -> str:
    """The numba type of one kernel argument as a short string, without importing numba.

    Arrays: ``dtype:ndim layout`` with ``r`` when read-only (``f4:2C``, ``u1:1Cr``);
    scalars: their dtype (``i8`` for int, ``f8`` for float, ``b1`` for bool). Anything else is
    ``?`` and goes to the JIT.
    """
    if isinstance(value, np.ndarray):
        dtype = value.dtype
        if (type(value) is not np.ndarray or not dtype.isnative or dtype.hasobject
                or dtype.fields is not None):
            return "?"  # subclasses (masked arrays, ...) and records: the JIT decides
        flags = value.flags
        layout = "C" if flags.c_contiguous else ("F" if flags.f_contiguous else "A")
        return f"{dtype.str[1:]}:{value.ndim}{layout}{'' if flags.writeable else 'r'}"
    kind = type(value)
    if kind is bool or kind is np.bool_:
        return "b1"
    if kind is int:
        return "i8"
    if kind is float:
        return "f8"
    if isinstance(value, np.generic) and value.dtype.isnative and value.dtype.kind in "iufb":
        return value.dtype.str[1:]
    return "?"


def _source_path(module_name: str) -> Path:
    spec = importlib.util.find_spec(module_name)
    if spec is None or spec.origin is None:
        raise ImportError(f"no module {module_name}")
    return Path(spec.origin)


def _cpu_id() -> bytes:
    """What the compiled code depends on besides its source: machine and instruction sets."""
    ident = os.uname().machine.encode() if hasattr(os, "uname") else sys.platform.encode()
    try:
        with open("/proc/cpuinfo", "rb") as handle:
            for line in handle:
                if line.startswith((b"flags", b"Features", b"model name")):
                    ident += line
                if line.strip() == b"":
                    break  # the first processor describes them all
    except OSError:
        pass
    return ident


def table_path(module_name: str) -> Path:
    """The signature table of a kernel module: ``<module>.aot.json`` beside its source."""
    source = _source_path(module_name)
    return source.with_name(source.stem + ".aot.json")


#: bump when :func:`arg_key`, :func:`_numba_type` or the flags of :func:`build` change: the
#: compiled modules' names change with it, so older builds are not loaded
ABI = 1


def aot_module_name(module_name: str) -> str:
    """The name of the compiled module for the current source, table, ABI and CPU."""
    # the compiled module is linked against numpy's C API (array boxing) and this Python
    digest = hashlib.sha256(f"octofactor-aot-{ABI} numpy-{np.__version__}".encode())
    for path in (_source_path(module_name), table_path(module_name)):
        digest.update(path.read_bytes())
    digest.update(_cpu_id())
    package, _, base = module_name.rpartition(".")
    return f"{package}.{base}_aot_{digest.hexdigest()[:16]}"


class Kernels:
    """The kernels of one module: compiled ahead of time where the arguments' types match a
    compiled signature, numba's JIT otherwise (see the module docstring).

    Attributes
    ----------
    module_name : the ``@njit`` kernels' module (imported only when the JIT is needed)
    compiled : the compiled extension module, or None (not built, stale, or switched off)
    """

    def __init__(self, module_name: str):
        self.module_name = module_name
        self.compiled = None
        self._table: dict[str, list[list[str]]] = {}
        if not _JIT_ONLY:
            try:
                self.compiled = importlib.import_module(aot_module_name(module_name))
                self._table = json.loads(table_path(module_name).read_text())
            except (ImportError, OSError, ValueError):
                self.compiled, self._table = None, {}
        self.jit_only = False  # tests switch the compiled kernels off for a comparison
        self.jit_calls = 0  # calls of a compiled kernel that went to the JIT (no signature)

    def __repr__(self) -> str:
        how = "JIT only" if self.compiled is None else self.compiled.__name__
        return f"Kernels({self.module_name!r}, {how})"

    def jit_module(self):
        return importlib.import_module(self.module_name)

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        signatures = self._table.get(name)
        if signatures is None and _RECORD is None:
            value = getattr(self.jit_module(), name)  # a constant, or a kernel not compiled
        else:
            value = self._dispatcher(name, signatures or [])
        setattr(self, name, value)
        return value

    def _dispatcher(self, name: str, signatures: list[list[str]]) -> Callable:
        compiled = {tuple(sig): getattr(self.compiled, f"{name}__{i}")
                    for i, sig in enumerate(signatures)}
        record = (_recorded.setdefault(self.module_name, {}).setdefault(name, set())
                  if _RECORD is not None else None)
        owner = self

        def call(*args):
            key = tuple(arg_key(a) for a in args)
            if record is not None:
                record.add(key)
            fn = None if owner.jit_only else compiled.get(key)
            if fn is None:
                owner.jit_calls += not owner.jit_only
                fn = getattr(owner.jit_module(), name)
            return fn(*args)

        call.__name__ = call.__qualname__ = name
        call.__doc__ = f"{self.module_name}.{name}, compiled ahead of time where it can be"
        return call


_LOADED: dict[str, Kernels] = {}


def kernels(module_name: str) -> Kernels:
    """The (cached) :class:`Kernels` namespace of a module of ``@njit`` kernels."""
    loaded = _LOADED.get(module_name)
    if loaded is None:
        loaded = _LOADED[module_name] = Kernels(module_name)
    return loaded


def format_table(table: dict[str, list[list[str]]]) -> str:
    """A signature table as JSON, one signature a line."""
    lines = []
    for name in sorted(table):
        sigs = ",\n".join("  " + json.dumps(list(sig)) for sig in sorted(table[name]))
        lines.append(f" {json.dumps(name)}: [\n{sigs}\n ]")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def _write_record() -> None:
    """Add the signatures called in this process to the modules' tables (OCTOFACTOR_AOT_RECORD=1:
    run the tests so, then ``make setup`` compiles them)."""
    for module_name, names in _recorded.items():
        path = table_path(module_name)
        try:
            table = json.loads(path.read_text())
        except (OSError, ValueError):
            table = {}
        for name, keys in names.items():
            merged = {tuple(k) for k in table.get(name, [])} | keys
            table[name] = [list(k) for k in merged if "?" not in k]
        table = {name: sigs for name, sigs in table.items() if sigs}
        path.write_text(format_table(table))


if _RECORD is not None:
    import atexit

    atexit.register(_write_record)


# ---------------------------------------------------------------------------- build
def _numba_type(key: str):
    from numba import types
    from numba.np.numpy_support import from_dtype

    if ":" not in key:
        return from_dtype(np.dtype(key))
    dtype, shape = key.split(":")
    digits = "".join(c for c in shape if c.isdigit())
    layout, flags = shape[len(digits)], shape[len(digits) + 1:]
    return types.Array(from_dtype(np.dtype(dtype)), int(digits), layout, readonly="r" in flags)


_BUILD_CACHE = None


def _isolate_numba_cache() -> None:
    """Point numba's on-disk cache at an empty temporary folder for this process.

    The cache holds machine code only, and the ahead-of-time compiler links the kernels' LLVM
    IR: a kernel loaded from the cache could not be linked. numba reads NUMBA_CACHE_DIR when
    it is imported, so this must come first (``python -m estimation.aot build``).
    """
    global _BUILD_CACHE
    if _BUILD_CACHE is not None:
        return
    if "numba" in sys.modules:
        raise RuntimeError("estimation.aot.build runs in a fresh process: "
                           "python -m estimation.aot build")
    import tempfile

    _BUILD_CACHE = tempfile.TemporaryDirectory(prefix="octofactor-aot-cache-")
    os.environ["NUMBA_CACHE_DIR"] = _BUILD_CACHE.name


def build(module_name: str, verbose: bool = False) -> Path:
    """Compile the kernels of ``module_name`` for every signature of its table into
    ``<package>/<module>_aot_<hash>.<ext suffix>`` (written under a temporary name, then
    renamed: an interrupted build leaves no module behind). Older builds are removed."""
    import sysconfig
    import tempfile
    import warnings

    _isolate_numba_cache()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc is pending deprecation
        import numba.pycc.compiler as pycc_compiler
        from numba.pycc import CC

    class _ReleaseGil(pycc_compiler.Flags):
        """The flags numba.pycc compiles with, and the GIL released around each call (as
        ``@njit(nogil=True)``), so that scan shares marked on threads run in parallel."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    module = importlib.import_module(module_name)
    table = json.loads(table_path(module_name).read_text())
    target = aot_module_name(module_name)
    package, _, base = target.rpartition(".")
    source = _source_path(module_name)
    suffix = sysconfig.get_config_var("EXT_SUFFIX")
    with tempfile.TemporaryDirectory(prefix="octofactor-aot-", dir=source.parent) as tmp:
        cc = CC(base, source_module=module)
        cc.output_dir = tmp
        cc.target_cpu = "host"
        cc.verbose = verbose
        for name, signatures in sorted(table.items()):
            fn = getattr(module, name).py_func
            for i, sig in enumerate(signatures):
                cc.export(f"{name}__{i}", tuple(_numba_type(k) for k in sig))(fn)
        saved = pycc_compiler.Flags
        pycc_compiler.Flags = _ReleaseGil
        try:
            cc.compile()
        finally:
            pycc_compiler.Flags = saved
        built = Path(tmp) / cc.output_file
        final = source.parent / (base + suffix)
        os.replace(built, final)
    prefix = source.stem + "_aot_"
    for old in source.parent.glob(prefix + "*"):
        if old != final and old.name.endswith(suffix):
            old.unlink()
    return final


def main(argv: list[str] | None = None) -> int:
    import argparse
    import time

    ap = argparse.ArgumentParser(prog="python -m estimation.aot",
                                 description="compile numba kernels ahead of time")
    sub = ap.add_subparsers(dest="action", required=True)
    b = sub.add_parser("build", help="compile the kernel modules (default: all of MODULES)")
    b.add_argument("modules", nargs="*", default=list(MODULES))
    b.add_argument("--if-stale", action="store_true",
                   help="only the modules whose compiled module is missing or out of date")
    b.add_argument("-v", "--verbose", action="store_true")
    s = sub.add_parser("status", help="which kernel modules are compiled and current")
    s.add_argument("modules", nargs="*", default=list(MODULES))
    args = ap.parse_args(argv)
    for module_name in args.modules:
        name = aot_module_name(module_name)
        current = importlib.util.find_spec(name) is not None
        if args.action == "status":
            print(f"{module_name}: {'compiled, current' if current else 'JIT only'} ({name})")
            continue
        if current and args.if_stale:
            print(f"{module_name}: compiled module is current")
            continue
        start = time.perf_counter()
        path = build(module_name, verbose=args.verbose)
        print(f"{module_name}: compiled ahead of time into {path} "
              f"({time.perf_counter() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
