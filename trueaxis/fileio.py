"""Writing files so that nothing half-written is ever left behind, and nothing the user did not name is overwritten.

The output gate, used by every writer and by the CLI before any work starts:

- a file is written as a temporary file in the same folder, then ``os.replace`` (atomic on POSIX file systems); on any
  error, ``KeyboardInterrupt`` included, the temporary file is removed and the old file is left as it was;
- a symbolic link is written *through*: its target is replaced and the link kept (as editors do), never the link;
- a device, FIFO or socket, or a folder where a file is expected (and a file where a folder is expected), is refused;
- a new file gets the permissions the user's umask gives (``mkstemp`` alone would leave 0600); a replaced file keeps
  its own permissions;
- :func:`check_outputs` refuses an output that is one of the inputs or another output, before anything is written.
"""

from __future__ import annotations

import os
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator


class OutputPathError(ValueError):
    """An output path the gate refuses (a device, a folder for a file, an input named as output, ...)."""


class Interrupted(BaseException):
    """The process was asked to stop (``signum``: SIGINT or SIGTERM) while it worked: what was not yet published is
    not written."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


_signalled: int | None = None


def note_signal(signum: int) -> None:
    """Record a SIGINT / SIGTERM (the application's signal handler calls it before raising): every later publish of
    an output refuses with :class:`Interrupted`, even when the exception the handler raised was lost inside compiled
    code that called back into Python (the output is then never written as if nothing had happened)."""
    global _signalled
    _signalled = signum


def raise_if_signalled() -> None:
    """Raise :class:`Interrupted` when :func:`note_signal` recorded a signal."""
    if _signalled is not None:
        raise Interrupted(_signalled)


def _umask() -> int:
    """The process' umask (read without changing it for longer than the call)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def new_file_mode() -> int:
    """Permission bits of a file created now by ``open(path, 'w')``: 0666 less the umask."""
    return 0o666 & ~_umask()


def new_folder_mode() -> int:
    """Permission bits of a folder created now by ``mkdir``: 0777 less the umask."""
    return 0o777 & ~_umask()


def resolve_output(path: str | os.PathLike, *, folder: bool = False) -> Path:
    """Where an output named ``path`` really goes (symbolic links followed), after checking it may be written there.

    folder : the output is a folder (a report folder) rather than a file.
    Raises OutputPathError for a device, FIFO or socket, a folder where a file is expected or the other way round, and
    a parent that exists but is not a folder.
    """
    given = Path(path)
    if str(path) == "":
        raise OutputPathError("an output path is empty")
    real = Path(os.path.realpath(given))
    if real.exists():
        mode = real.stat().st_mode
        if folder:
            if not stat.S_ISDIR(mode):
                raise OutputPathError(f"{given}: exists and is not a folder")
        elif stat.S_ISDIR(mode):
            raise OutputPathError(f"{given}: is a folder; name a file to write")
        elif not stat.S_ISREG(mode):
            raise OutputPathError(f"{given}: is not a regular file (a device, FIFO or socket); refusing to write it")
    parent = real.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputPathError(f"{given}: {parent} is not a folder")
    return real


def _same(a: Path, b: Path) -> bool:
    if a.exists() and b.exists():
        return os.path.samefile(a, b)
    return os.path.realpath(a) == os.path.realpath(b)


def check_outputs(inputs: Iterable[tuple[str, str | os.PathLike | None]],
                  outputs: Iterable[tuple[str, str | os.PathLike | None, bool]]) -> None:
    """Refuse, before any work, outputs that would destroy an input or each other.

    inputs : (option name, path or None) pairs; outputs : (option name, path or None, folder) triples, folder False for a
    file, True for a folder written into, "replaced" for a folder replaced whole (it may hold only what trueaxis
    published there: :func:`check_replaceable_folder`). None entries
    (options not given) are skipped. An output folder may not contain an input file either (the old report folder is
    replaced whole). Raises OutputPathError naming both options.
    """
    outputs = list(outputs)
    for name, p, folder in outputs:
        if p is not None and str(p).strip() == "":
            raise OutputPathError(f"{name}: an empty path; name the output")
        if folder and str(p) == "-":  # (a file output may be '-', standard output, where its command says so)
            raise OutputPathError(f"{name} -: a folder cannot go to standard output; name a folder")
    ins = [(name, Path(p)) for name, p in inputs if p is not None and str(p) != "-"]
    outs = [(name, Path(p), folder) for name, p, folder in outputs if p is not None and str(p) != "-"]
    for name, out, folder in outs:
        resolve_output(out, folder=folder)
        if folder == "replaced":
            check_replaceable_folder(out)
        for in_name, inp in ins:
            inside = folder and out.exists() and inp.exists() and \
                Path(os.path.realpath(inp)).is_relative_to(Path(os.path.realpath(out)))
            if _same(out, inp) or inside:
                given = f" ({in_name})" if in_name.startswith("-") else ""  # an option's name; a positional's is not
                raise OutputPathError(f"{name} {out} would overwrite the input {inp}{given}; name another output")
    for i, (name_a, a, _) in enumerate(outs):
        for name_b, b, _ in outs[i + 1:]:
            if _same(a, b):
                raise OutputPathError(f"{name_a} and {name_b} name the same file {a}; name two outputs")
    # a folder replaced whole holds only what its writer publishes there: another output inside it would be lost
    # with the old folder, or (written first) refuse the folder's replacement after all the work
    for name_a, a, folder in outs:
        for name_b, b, _ in outs:
            if folder == "replaced" and b is not a and \
                    Path(os.path.realpath(b)).is_relative_to(Path(os.path.realpath(a))):
                raise OutputPathError(f"{name_b} {b} lies inside {name_a} {a}, a folder replaced whole; name a "
                                      f"{name_b} outside it")


class WriteRefused(OSError):
    """The system refused a place to write an output: its ``filename`` is the user's path (the temporary one beside
    it is never named). An OSError of its own class: OSError(ENOENT, ...) would become FileNotFoundError, a missing
    input to the CLI (exit 2), where this is the system's refusal (exit 1) as for every other output."""


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary file beside ``path`` for writers that want a file name (exporters): when the block ends without an
    error the temporary file replaces ``path`` (through a symbolic link, with the permissions described above); on an
    error it is removed and ``path`` is left as it was."""
    target = resolve_output(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    mode = stat.S_IMODE(target.stat().st_mode) if target.exists() else new_file_mode()
    try:
        fd, temp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:  # name the user's path, not the temporary one
        raise WriteRefused(exc.errno, f"cannot write here: {exc.strerror}", str(path)) from None
    os.close(fd)
    try:
        yield Path(temp)
        os.chmod(temp, mode)
        raise_if_signalled()
        os.replace(temp, target)
    except BaseException:
        if os.path.exists(temp):
            os.unlink(temp)
        raise


def atomic_write(path: str | os.PathLike, data, encoding: str = "utf-8") -> Path:
    """Write ``data`` to ``path`` atomically (flushed to disk first); text is encoded without newline translation.
    data : str, bytes, or a list of bytes-like pieces (bytes, C-contiguous numpy arrays) written one after the other,
    so that a large array is not first copied into one bytes object. Returns the path."""
    if isinstance(data, str):
        pieces = [data.encode(encoding)]
    elif isinstance(data, list):
        pieces = [memoryview(piece).cast("B") for piece in data]
    else:
        pieces = [bytes(data)]
    with atomic_path(path) as temp:
        with open(temp, "wb") as f:
            for piece in pieces:
                f.write(piece)
            f.flush()
            os.fsync(f.fileno())
    return Path(path)


#: The file every published folder carries, listing the files published with it: such a folder may be replaced whole
#: by the next run as long as it holds nothing else.
FOLDER_MARKER = ".trueaxis-output"


def _published_names(folder: Path) -> set | None:
    """The names a folder trueaxis published holds (its marker's list, or the ``files`` of a trueaxis report.json or
    the fixed names of a diagnosis written before the marker), or None for a folder trueaxis did not publish."""
    marker = folder / FOLDER_MARKER
    if marker.is_file():
        lines = marker.read_text(encoding="utf-8").splitlines()
        return {line for line in lines[1:] if line} | {FOLDER_MARKER}
    report = folder / "report.json"
    if report.is_file():
        import json

        try:
            data = json.loads(report.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        if isinstance(data, dict) and data.get("trueaxis_report") and isinstance(data.get("files"), list):
            return {str(name) for name in data["files"]}
    diagnosis = folder / "diagnosis.json"
    if diagnosis.is_file():  # a diagnosis report written before the marker: its fixed names
        import json

        try:
            data = json.loads(diagnosis.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        if isinstance(data, dict) and {"format", "verdict", "gap_um"} <= set(data):
            return set(DIAGNOSIS_FILES_BEFORE_MARKER)
    return None


#: The files of a diagnosis report folder written before the folders had their marker.
DIAGNOSIS_FILES_BEFORE_MARKER = ("diagnosis.json", "diagnosis.html", "gap_map.png", "gap_vs_state.png",
                                 "candidates.png", "before_after.png")


def check_replaceable_folder(path: str | os.PathLike) -> None:
    """Refuse to replace a folder that holds files trueaxis did not write there: an existing ``path`` may be replaced
    whole only when it is empty or holds only what trueaxis published in it (:func:`_published_names`). Raises
    OutputPathError naming a few of the other files."""
    real = Path(os.path.realpath(path))
    if not real.is_dir():
        return
    names = set(os.listdir(real))
    published = _published_names(real) or set()
    foreign = sorted(names - published)
    if not foreign:
        return
    shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
    raise OutputPathError(f"{path}: holds files trueaxis did not write there ({shown}); the report replaces its "
                          "output folder whole: name a new or empty folder")


def temp_folder_beside(out: Path, suffix: str = ".tmp") -> Path:
    """A new temporary folder beside the output folder ``out`` (its parent created), to be published as ``out``
    (:func:`publish_folder`). A place the system does not let us write is said naming the user's path (not the
    temporary one) as the system's refusal (exit 1): /proc said 'No such file or directory' about a name the user
    never gave, exit 2."""
    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=suffix, dir=out.parent))
    except OSError as exc:
        raise WriteRefused(exc.errno, f"cannot write here: {exc.strerror}", str(out)) from None


def publish_folder(temp: Path, out: Path) -> None:
    """Move a finished temporary folder ``temp`` into place as ``out`` (an old ``out`` is replaced whole, when
    :func:`check_replaceable_folder` allows it), with the umask's permissions (``mkdtemp`` makes 0700). The folder
    gets :data:`FOLDER_MARKER`, listing its files, so that a later run may replace it."""
    out = resolve_output(out, folder=True)
    check_replaceable_folder(out)
    names = sorted(os.listdir(temp))
    (Path(temp) / FOLDER_MARKER).write_text("written by trueaxis; replaced whole by the next run as long as it holds "
                                            "only these files:\n" + "".join(f"{n}\n" for n in names),
                                            encoding="utf-8")
    raise_if_signalled()
    os.chmod(temp, new_folder_mode())
    old = None
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
        os.rmdir(old)
        os.replace(out, old)
    try:
        os.replace(temp, out)
    except BaseException:
        if old is not None:
            os.replace(old, out)
        raise
    if old is not None:
        import shutil

        shutil.rmtree(old, ignore_errors=True)


def json_ready(value):
    """A value as strict JSON can hold it: numpy scalars and arrays to Python, non-finite floats to None (JSON has
    no Infinity or NaN: ``json.dumps`` writes them by default, and a strict reader, a browser's JSON.parse, refuses
    the file)."""
    import math

    import numpy as np

    def ready(v):  # (the imports once, not at every element of a report's long lists)
        if isinstance(v, dict):
            return {str(k): ready(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [ready(x) for x in v]
        if isinstance(v, np.ndarray):
            return ready(v.tolist())
        if isinstance(v, (np.floating, float)):
            return float(v) if math.isfinite(v) else None
        if isinstance(v, np.integer):
            return int(v)
        if isinstance(v, np.bool_):
            return bool(v)
        return v

    return ready(value)


def json_text(value, indent: int | None = 2) -> str:
    """Strict JSON text of ``value`` (``json_ready``)."""
    import json

    return json.dumps(json_ready(value), indent=indent, allow_nan=False)
