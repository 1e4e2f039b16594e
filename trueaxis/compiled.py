"""The post's compiled kernels: numba's JIT, or the same kernels compiled ahead of time (start-up without numba).

A post of a small program spends most of its start-up on numba, not on its work: importing numba (and the
``scipy.linalg`` it loads for its BLAS) about 0.15 s CPU, and its first kernel call (the typing and target context,
the cache index) about 0.3 s, for a post that takes 0.01 s. The kernel modules (:data:`KERNEL_MODULES`) therefore take
their ``numba`` from here: a stand-in whose ``njit`` returns a :class:`Kernel`, which

- calls the kernel's ahead-of-time compiled twin (``numba.pycc``, built by :func:`build_aot` into an extension module
  next to this file, ``_aot_kernels``) when one was built from the same source and the arguments have exactly the
  types it was compiled for (dtype, dimensions, C order, writable where it writes), so that numba is never imported;
- else imports numba and turns every kernel into the numba dispatcher it always was (``numba.njit(**options)`` of the
  same function: the same cache), and calls that.

The ahead-of-time twins are the same functions compiled by the same compiler (numba's, through LLVM; no fast-math, no
fused multiply-add either way), so they give the same numbers bit for bit; ``tests/test_compiled.py`` posts programs
both ways and compares the bytes. A build whose source no longer matches the kernel modules (a source hash in its
spec file) is not used. ``TRUEAXIS_AOT=0`` switches the ahead-of-time twins off; ``TRUEAXIS_AOT_DIR`` names another
folder for them. ``python -m trueaxis.warm`` builds them (:func:`build_aot`, given the warm-up posts).

The parallel kernels (numba ``prange``, long programs) have no ahead-of-time twin (pycc compiles serial code only).
The twins release the GIL instead (compiled so, :class:`_releasing_the_gil`), and a long program's twin runs the
serial kernels' twins on threads, each on its share of the poses (:func:`run_twins`; ``machine.twin``,
``machine.error_kernel``): the same numbers pose by pose, and numba is not imported at all (its import and first
cache load cost a long post about 0.7 s). Without twins the parallel kernels import numba when first used.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.machinery
import importlib.util
import json
import os
import sys
import threading
from pathlib import Path

import numpy as np

__all__ = ["numba", "Kernel", "KERNEL_MODULES", "build_aot", "aot_available", "numba_imported", "THREADS_MIN",
           "thread_slices", "run_twins", "run_threads", "kernels_on_this_thread", "kernels_shared"]

KERNEL_MODULES = ("trueaxis.nc.fast_read", "trueaxis.nc.fast_interp", "trueaxis.nc.fast_write",
                  "trueaxis.machine.error_kernel", "trueaxis.machine.chain_kernel", "trueaxis.inspect.kernels",
                  "trueaxis.postproc.newton_kernel")
AOT_NAME = "_aot_kernels"
_HERE = Path(__file__).resolve().parent
_UNSET = object()

_kernels: list = []  # every Kernel made
_real = None  # the numba module, once imported
_aot = _UNSET  # {qualified kernel name: (function, argument spec)} or None


# From this many poses on, a kernel's work is shared among threads (numba prange, or ahead-of-time twins on threads).
THREADS_MIN = 4096
_pool = None


def thread_count() -> int:
    """Threads for the kernels' parallel work: NUMBA_NUM_THREADS, as numba's parallel kernels take it, else the CPU
    count."""
    return max(1, int(os.environ.get("NUMBA_NUM_THREADS") or 0) or os.cpu_count() or 1)


_here = threading.local()


class kernels_on_this_thread:
    """Within: the kernels called from this thread run on it alone, whatever the number of poses (no share for the
    kernels' threads, no numba parallel kernel): for work that runs on threads of its own already (the post's chunks
    of moves side by side). Each pose is computed alone either way: the same numbers."""

    def __enter__(self):
        self._before = getattr(_here, "serial", False)
        _here.serial = True
        return self

    def __exit__(self, *exc):
        _here.serial = self._before
        return False


def kernels_shared(n: int) -> bool:
    """Is the work on ``n`` poses worth sharing among threads (THREADS_MIN and more), and may it be shared here (not
    inside :class:`kernels_on_this_thread`)?"""
    return n >= THREADS_MIN and not getattr(_here, "serial", False)


def thread_slices(n: int) -> list:
    """Contiguous slices of ``range(n)``, one per thread, when ``n`` is worth sharing (THREADS_MIN and more) and
    there is more than one thread; else [] (also inside :class:`kernels_on_this_thread`)."""
    t = thread_count()
    if t < 2 or not kernels_shared(n):
        return []
    edges = [n * k // t for k in range(t + 1)]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]


def run_twins(kernel, calls):
    """Run ``kernel`` on each argument tuple of ``calls`` by its ahead-of-time twin, the calls on threads of their own
    (the twins release the GIL): the list of results, or None when a call has no twin (the caller takes numba's
    parallel kernel instead). Each call computes what it would alone: the same numbers as one call, or as numba's
    parallel kernel, which does the same pose by pose."""
    twin = getattr(kernel, "twin", None)  # (numba's dispatcher once the twins are off: none)
    fns = [twin(*args) for args in calls] if twin is not None else [None]
    if any(fn is None for fn in fns):
        return None
    return run_threads(lambda fa: fa[0](*fa[1]), list(zip(fns, calls)))


def _forget_pool():
    """In a forked child: the parent's kernel threads are not there (a new pool is made when needed)."""
    global _pool
    _pool = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def run_threads(fn, items) -> list:
    """``[fn(item) for item in items]``, the calls on the kernels' threads (``fn`` should spend its time in twins,
    which release the GIL, and must not call ``run_threads`` itself: the threads would wait for each other)."""
    global _pool
    if _pool is None:
        from concurrent.futures import ThreadPoolExecutor

        _pool = ThreadPoolExecutor(max_workers=thread_count(), thread_name_prefix="trueaxis-kernel")
    return list(_pool.map(fn, items))


def numba_imported() -> bool:
    """True once a kernel needed numba (and so imported it)."""
    return _real is not None


class Kernel:
    """A kernel function: its ahead-of-time twin where it fits the arguments, else its numba dispatcher."""

    def __init__(self, fn, options):
        functools.update_wrapper(self, fn)
        self.py_func = fn
        self.options = options
        self.key = f"{fn.__module__}.{fn.__qualname__}"
        self.dispatcher = None
        _kernels.append(self)

    def __call__(self, *args):
        # The ahead-of-time twin first, also once numba is in (a long program's parallel kernels need it): loading a
        # kernel from numba's cache costs about 0.07 s, the twin nothing.
        table = _aot if _aot is not _UNSET else _load_aot()
        if table is not None:
            for fn, spec in table.get(self.key, ()):
                if _fits(args, spec):
                    return fn(*args)
        if self.dispatcher is None:
            _jit_all()
        return self.dispatcher(*args)

    def twin(self, *args):
        """The ahead-of-time twin that takes exactly these arguments, or None (then only numba would). Twins release
        the GIL while they run: callers may run them on threads of their own."""
        table = _aot if _aot is not _UNSET else _load_aot()
        for fn, spec in (table or {}).get(self.key, ()):
            if _fits(args, spec):
                return fn
        return None

    def __getattr__(self, name):  # dispatcher attributes (signatures, overloads ...): numba's
        if name.startswith("__") or name in ("py_func", "options", "key", "dispatcher", "twin"):
            raise AttributeError(name)
        _jit_all()
        return getattr(self.dispatcher, name)

    def __repr__(self):
        return f"<trueaxis kernel {self.key}>"


class _NumbaStandIn:
    """What a kernel module calls ``numba``: ``njit`` makes :class:`Kernel` objects; anything else is numba's own
    (imported then)."""

    def njit(self, *args, **options):
        if args and callable(args[0]):
            return Kernel(args[0], options)
        return lambda fn: Kernel(fn, options)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        _jit_all()
        return getattr(_real, name)


numba = _STAND_IN = _NumbaStandIn()


def _jit_all():
    """Import numba and make every kernel its numba dispatcher; the kernel modules' globals (``numba`` and the
    kernels, which compiled kernels call) become the real ones, as if they had imported numba themselves -- but for
    the kernels with an ahead-of-time twin, which stay :class:`Kernel` objects so that Python's calls still reach the
    twin (no compiled kernel calls one of them: they are the ones the post calls from Python)."""
    global _real
    if _real is None:
        import numba as real

        _real = real
    for k in _kernels:
        if k.dispatcher is None:
            k.dispatcher = _real.njit(**k.options)(k.py_func)
    for name, mod in list(sys.modules.items()):
        if mod is None or not name.startswith("trueaxis") or name == __name__:
            continue
        d = vars(mod)
        if d.get("numba") is _STAND_IN:
            d["numba"] = _real
        twins = _aot if isinstance(_aot, dict) else {}
        for key, v in list(d.items()):
            if isinstance(v, Kernel) and v.key not in twins:
                d[key] = v.dispatcher


# --------------------------------------------------------------------------------------- ahead-of-time twins -----


def _aot_dir() -> Path:
    return Path(os.environ.get("TRUEAXIS_AOT_DIR") or _HERE)


def _source_files() -> list:
    out = []
    for name in KERNEL_MODULES:
        parts = name.split(".")[1:]
        out.append(_HERE.joinpath(*parts[:-1], parts[-1] + ".py"))
    return out


def _source_hash() -> str | None:
    """SHA-256 over the kernel modules' source, Python's and numpy's versions; None when a kernel module is not where
    :data:`KERNEL_MODULES` says (moved: no ahead-of-time twins until the list follows)."""
    h = hashlib.sha256(f"{sys.version_info[:2]} numpy {np.__version__}\n".encode())
    for path in _source_files():
        if not path.is_file():
            return None
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _load_aot():
    """The ahead-of-time twins, or None (switched off, not built, or built from other source)."""
    global _aot
    _aot = None
    if os.environ.get("TRUEAXIS_AOT", "1") == "0":
        return None
    folder = _aot_dir()
    spec_path = folder / f"{AOT_NAME}.json"
    if not spec_path.is_file():
        return None
    try:
        spec = json.loads(spec_path.read_text())
        source = _source_hash()
        if source is None or spec.get("source") != source:
            return None
        lib = folder / spec["file"]
        loader = importlib.machinery.ExtensionFileLoader(AOT_NAME, str(lib))
        mod_spec = importlib.util.spec_from_file_location(AOT_NAME, str(lib), loader=loader)
        mod = importlib.util.module_from_spec(mod_spec)
        loader.exec_module(mod)
        _aot = {key: [(getattr(mod, e["export"]), [tuple(a) for a in e["args"]]) for e in entries]
                for key, entries in spec["kernels"].items()}
    except (OSError, ValueError, KeyError, ImportError, AttributeError):
        _aot = None
    return _aot


_INT_MIN, _INT_MAX = -(2**63), 2**63 - 1


def _fits(args, spec) -> bool:
    """Do ``args`` have exactly the types the twin was compiled for? (Anything else would not be converted by it.)"""
    if len(args) != len(spec):
        return False
    for a, s in zip(args, spec):
        kind = s[0]
        if kind == "a" or kind == "F":  # an array in C (or Fortran) order
            if type(a) is not np.ndarray or a.dtype.str != s[1] or a.ndim != s[2] or not a.flags.aligned \
                    or not (a.flags.c_contiguous if kind == "a" else a.flags.f_contiguous) \
                    or (s[3] and not a.flags.writeable):
                return False
        elif kind == "i":
            if isinstance(a, (bool, np.bool_)) or not isinstance(a, (int, np.int64)) or not _INT_MIN <= a <= _INT_MAX:
                return False
        elif kind == "b":
            if not isinstance(a, (bool, np.bool_)):
                return False
        elif kind == "f":
            if type(a) is not float and type(a) is not np.float64:
                return False
        else:
            return False
    return True


def _arg_spec(ty):
    """A numba argument type as _fits reads it."""
    from numba.core import types

    if isinstance(ty, types.Array):
        if ty.layout not in ("C", "F") or not ty.aligned:
            raise TypeError(f"not exported: array layout {ty}")
        return ["a" if ty.layout == "C" else "F", np.dtype(str(ty.dtype)).str, ty.ndim, bool(ty.mutable)]
    if isinstance(ty, types.Boolean):
        return ["b"]
    if isinstance(ty, types.Integer) and ty.bitwidth == 64 and ty.signed:
        return ["i"]
    if isinstance(ty, types.Float) and ty.bitwidth == 64:
        return ["f"]
    raise TypeError(f"not exported: argument type {ty}")


def build_aot(warm_up, folder: Path | None = None, out=sys.stderr) -> Path:
    """Compile the kernels the post calls, for the argument types it calls them with, ahead of time into an
    extension module in ``folder`` (default: next to this file); returns the spec file's path.

    The types are those of a warm-up post (``trueaxis.warm``'s programs on every fixture machine, in every mode):
    every kernel a post calls from Python with numba dispatchers holding those signatures is exported.
    ``warm_up(out=...)`` runs those posts (the application passes ``trueaxis.warm.warm``: this base module imports
    nothing above it)."""
    import tempfile

    from numba.pycc import CC

    global _aot
    folder = Path(folder) if folder else _aot_dir()
    folder.mkdir(parents=True, exist_ok=True)
    _aot = None  # the warm-up below must reach numba's dispatchers (they record the signatures exported), not a build
    source = _source_hash()
    if source is None:
        raise FileNotFoundError(f"a kernel module of {', '.join(KERNEL_MODULES)} is not in {_HERE}")
    for name in KERNEL_MODULES:
        importlib.import_module(name)
    _jit_all()
    with open(os.devnull, "w") as devnull:
        warm_up(out=devnull)
    cc = CC(AOT_NAME)
    cc.verbose = False
    kernels = {}
    called = _called_from_python()
    for k in _kernels:
        if k.key not in called or k.py_func.__module__ not in KERNEL_MODULES:
            continue  # (a kernel outside the hashed modules would never be known stale)
        if k.options.get("parallel"):
            continue  # pycc compiles serial code only: left to numba
        for i, sig in enumerate(k.dispatcher.nopython_signatures):
            try:
                args = [_arg_spec(t) for t in sig.args]
            except TypeError as exc:
                print(f"trueaxis.compiled: {k.key}: {exc}", file=out)
                continue
            export = f"{k.key.replace('.', '__')}__{i}"
            cc.export(export, sig)(k.py_func)
            kernels.setdefault(k.key, []).append({"export": export, "args": args, "signature": str(sig)})
    with tempfile.TemporaryDirectory() as tmp, _releasing_the_gil():
        cc.output_dir = tmp
        cc.compile()
        built = next(Path(tmp).glob(f"{AOT_NAME}*"))
        target = folder / built.name
        os.replace(built, target) if built.stat().st_dev == folder.stat().st_dev else target.write_bytes(
            built.read_bytes())
    spec_path = folder / f"{AOT_NAME}.json"
    spec_path.write_text(json.dumps({"file": target.name, "source": source, "kernels": kernels}, indent=1))
    print(f"trueaxis.compiled: {sum(map(len, kernels.values()))} kernel signatures compiled ahead of time into "
          f"{target}", file=out)
    return spec_path


class _releasing_the_gil:
    """While compiling ahead of time: every exported kernel's Python wrapper releases the GIL around the call
    (numba's ``nogil``; pycc takes its compile flags from ``numba.core.compiler.Flags``, which has no such option of
    its own). The kernels touch no Python object, so threads may run them side by side (``machine.twin``: the chain of
    a long program on all cores, without numba's parallel kernels)."""

    def __enter__(self):
        from numba.pycc import compiler

        self._module, self._flags = compiler, compiler.Flags

        class Flags(compiler.Flags):
            def __init__(self, *args, **kwargs):
                super().__init__(*args, **kwargs)
                self.release_gil = True

        compiler.Flags = Flags

    def __exit__(self, *exc):
        self._module.Flags = self._flags
        return False


def _called_from_python() -> set:
    """The kernels the post calls from Python (module-level names other modules or the post use), not helpers."""
    return {"trueaxis.nc.fast_read.line_starts", "trueaxis.nc.fast_read.scan_lines",
            "trueaxis.nc.fast_read.number_style", "trueaxis.nc.fast_read.next_check_candidate",
            "trueaxis.nc.fast_read.ijkr_after_linear",
            "trueaxis.nc.fast_interp.straight_run", "trueaxis.nc.fast_interp.run_lengths",
            "trueaxis.nc.fast_write.scan", "trueaxis.nc.fast_write.assemble", "trueaxis.nc.fast_write.pieces",
            "trueaxis.machine.error_kernel.evaluate_packed", "trueaxis.machine.chain_kernel.pose",
            "trueaxis.machine.chain_kernel.pose_and_axis_jacobian",
            "trueaxis.inspect.kernels.cone_normal_equations", "trueaxis.inspect.kernels.csv_rows",
            "trueaxis.inspect.kernels.cone_patch_distance", "trueaxis.postproc.newton_kernel.gauss_newton_step",
            "trueaxis.postproc.newton_kernel.solve_unloaded"}


def aot_available() -> bool:
    """Is an ahead-of-time build for the current source loadable?"""
    return (_aot if _aot is not _UNSET else _load_aot()) is not None

