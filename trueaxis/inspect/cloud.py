"""CMM point clouds in and out: PLY (ascii, binary little/big endian), CSV and XYZ (DESIGN.md §7).

A cloud is in the part frame, in mm. Bad input is refused, never repaired: an empty, unreadable or truncated file,
an unknown extension, NaN or infinite coordinates and normals of zero length each raise :class:`CloudError` with a
one-line message naming the file. Writing is atomic (temporary file in the same folder, then ``os.replace``), so an
error leaves nothing half-written behind.

The PLY reader is our own (numpy only): a general reader such as open3d's skips or zero-fills what it cannot parse,
and an inspection must not measure a part against points that were never there.
"""

from __future__ import annotations

import io
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..fileio import atomic_write

__all__ = ["Cloud", "CloudError", "read_cloud", "write_cloud_ply", "check_extent"]


class CloudError(ValueError):
    """A cloud file or array that cannot be used as a measurement; the message is one line naming the file."""


@dataclass(frozen=True)
class Cloud:
    """A measured point cloud.

    points : (n, 3) float64, mm, part frame
    normals : (n, 3) float64 unit vectors, or None when the file has none
    source : str, the file it was read from
    """

    points: np.ndarray
    normals: np.ndarray | None
    source: str

    def __len__(self) -> int:
        return len(self.points)


# PLY scalar types (both the PLY 1.0 names and the sized aliases) -> numpy type codes without byte order
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_NORMAL_NAMES = ("nx", "ny", "nz")


def read_cloud(path: str | os.PathLike) -> Cloud:
    """Read a CMM cloud from a ``.ply``, ``.csv`` or ``.xyz`` file.

    Parameters
    ----------
    path : file name; the extension (case-insensitive) selects the format:
        ``.ply``: ascii or binary (little or big endian); vertex properties ``x y z`` and optionally ``nx ny nz``, of any
        numeric type; other properties and elements are ignored. Elements with list properties (faces) may follow the
        vertices, not precede them in a binary file.
        ``.csv``: columns ``x,y,z[,nx,ny,nz]``, comma- or whitespace-separated; a header line naming the columns is
        optional (with a header, extra named columns are ignored); lines starting with ``#`` are comments.
        ``.xyz``: whitespace-separated ``x y z`` or ``x y z nx ny nz``.

    Returns
    -------
    Cloud with points (n, 3) float64 mm and normals (n, 3) float64 normalised to unit length, or None.

    Raises
    ------
    CloudError : empty, unreadable or truncated file, unknown extension, NaN or infinite values, zero-length normals.
    """
    path = Path(path)
    name = str(path)
    ext = path.suffix.lower()
    readers = {".ply": _read_ply, ".csv": _read_csv, ".xyz": _read_xyz}
    if ext not in readers:
        raise CloudError(f"{name}: unknown cloud extension {path.suffix!r} (expected .ply, .csv or .xyz)")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CloudError(f"{name}: cannot read the file ({exc.strerror or exc})") from exc
    if not data.strip():
        raise CloudError(f"{name}: the file is empty")
    points, normals = readers[ext](data, name)
    return _checked_cloud(points, normals, name)


def _checked_cloud(points: np.ndarray, normals: np.ndarray | None, name: str) -> Cloud:
    """Refuse empty clouds, non-finite values and zero normals; return float64 arrays with unit normals."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if len(points) == 0:
        raise CloudError(f"{name}: the cloud has no points")
    _refuse_non_finite(points, name, "coordinates")
    if normals is not None:
        normals = np.ascontiguousarray(normals, dtype=np.float64)
        _refuse_non_finite(normals, name, "normals")
        length = np.linalg.norm(normals, axis=1)
        # a normal written as float32 zeros is exactly zero; anything this short carries no direction either
        zero = length <= 1e-12
        if zero.any():
            first = int(np.flatnonzero(zero)[0])
            raise CloudError(f"{name}: {int(zero.sum())} of {len(normals)} normals have zero length "
                             f"(first at point {first}, counting from 0)")
        normals = normals / length[:, None]
    return Cloud(points=points, normals=normals, source=name)


def _refuse_non_finite(values: np.ndarray, name: str, what: str) -> None:
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        row = ", ".join(f"{v:g}" for v in values[first])
        raise CloudError(f"{name}: {int(bad.sum())} of {len(values)} points have NaN or infinite {what} "
                         f"(first at point {first}, counting from 0: [{row}])")


# ---------------------------------------------------------------------------------------------------------------- PLY

@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list  # (name, type code) for scalars, (name, (count code, item code)) for lists

    @property
    def has_lists(self) -> bool:
        return any(isinstance(t, tuple) for _, t in self.properties)


def _split_ply_header(data: bytes, name: str) -> tuple[list[str], bytes]:
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise CloudError(f"{name}: not a PLY file (it does not start with the line 'ply')")
    match = re.search(rb"(?m)^end_header[ \t]*\r?\n", data)  # at a line start: not inside a comment
    if match is None:
        # a header without its body: accept 'end_header' as the very last bytes too
        if data.rstrip().endswith(b"end_header"):
            end = len(data)
        else:
            raise CloudError(f"{name}: PLY header has no 'end_header' line (truncated or not a PLY file)")
        head = data[:end]
    else:
        end = match.end()
        head = data[:match.start()]
    try:
        lines = head.decode("ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise CloudError(f"{name}: PLY header is not ascii text (corrupt file?)") from exc
    return lines, data[end:]


def _parse_ply_header(lines: list[str], name: str) -> tuple[str | None, list[_PlyElement]]:
    byte_order = "missing"
    elements: list[_PlyElement] = []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        try:
            if key == "format":
                if words[1] not in _PLY_FORMATS:
                    raise CloudError(f"{name}: unknown PLY format {words[1]!r} in header line {number}")
                byte_order = _PLY_FORMATS[words[1]]
            elif key == "element":
                count = int(words[2])
                if count < 0:
                    raise ValueError
                elements.append(_PlyElement(words[1], count, []))
            elif key == "property":
                if not elements:
                    raise ValueError
                if words[1] == "list":
                    types = (_PLY_TYPES[words[2]], _PLY_TYPES[words[3]])
                    elements[-1].properties.append((words[4], types))
                else:
                    elements[-1].properties.append((words[2], _PLY_TYPES[words[1]]))
            elif key != "end_header":
                raise ValueError
        except CloudError:
            raise
        except (IndexError, KeyError, ValueError) as exc:
            raise CloudError(f"{name}: cannot parse PLY header line {number}: {line.strip()!r}") from exc
    if byte_order == "missing":
        raise CloudError(f"{name}: PLY header has no 'format' line")
    return byte_order, elements


def _read_ply(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    lines, body = _split_ply_header(data, name)
    byte_order, elements = _parse_ply_header(lines, name)
    index = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if index is None:
        raise CloudError(f"{name}: PLY header declares no 'vertex' element")
    vertex = elements[index]
    names = [p for p, _ in vertex.properties]
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise CloudError(f"{name}: PLY vertex element has no property {', '.join(missing)}")
    if vertex.has_lists:
        raise CloudError(f"{name}: PLY vertex element has list properties, which a point cloud cannot have")
    present = [n for n in _NORMAL_NAMES if n in names]
    if present and len(present) != 3:
        raise CloudError(f"{name}: PLY vertex element has {' '.join(present)} but not all of nx ny nz")
    if vertex.count == 0:
        raise CloudError(f"{name}: the cloud has no points (PLY header declares 0 vertices)")

    if byte_order is None:
        table = _ply_ascii_vertices(body, elements, index, name)
        columns = {n: table[:, names.index(n)] for n in names}
    else:
        table = _ply_binary_vertices(body, elements, index, byte_order, name)
        columns = {n: table[n] for n in names}
    points = np.column_stack([columns[c] for c in "xyz"]).astype(np.float64)
    normals = np.column_stack([columns[c] for c in _NORMAL_NAMES]).astype(np.float64) if present else None
    return points, normals


def _ply_binary_vertices(body: bytes, elements: list[_PlyElement], index: int, order: str, name: str) -> np.ndarray:
    offset = 0
    for element in elements[:index]:
        if element.has_lists:
            # the size of a list element is only known by walking it; no CMM writer puts faces before vertices
            raise CloudError(f"{name}: binary PLY with list element {element.name!r} before the vertices is not supported")
        offset += element.count * np.dtype([(p, order + t) for p, t in element.properties]).itemsize
    vertex = elements[index]
    dtype = np.dtype([(p, order + t) for p, t in vertex.properties])
    needed = offset + vertex.count * dtype.itemsize
    if len(body) < needed:
        raise CloudError(f"{name}: binary PLY is truncated: {vertex.count} vertices need {needed} bytes of data, "
                         f"the file has {len(body)}")
    trailing = body[needed:]
    if index == len(elements) - 1 and trailing.strip(b"\r\n"):
        raise CloudError(f"{name}: binary PLY has {len(trailing)} bytes after its {vertex.count} declared vertices "
                         f"(wrong vertex count in the header?)")
    return np.frombuffer(body, dtype=dtype, count=vertex.count, offset=offset)


def _ply_ascii_vertices(body: bytes, elements: list[_PlyElement], index: int, name: str) -> np.ndarray:
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError as exc:
        raise CloudError(f"{name}: ascii PLY body contains non-text bytes (corrupt or truncated file)") from exc
    lines = [line for line in text.splitlines() if line.strip()]
    start = sum(e.count for e in elements[:index])
    vertex = elements[index]
    rows = lines[start:start + vertex.count]
    if len(rows) < vertex.count:
        raise CloudError(f"{name}: ascii PLY is truncated: header declares {vertex.count} vertices, "
                         f"the file has {max(len(rows), 0)}")
    if index == len(elements) - 1 and len(lines) > start + vertex.count:
        raise CloudError(f"{name}: ascii PLY has {len(lines) - start - vertex.count} lines after its "
                         f"{vertex.count} declared vertices (wrong vertex count in the header?)")
    table = _parse_table(rows, None, name, "ascii PLY vertex")
    if table.shape[1] != len(vertex.properties):
        raise CloudError(f"{name}: ascii PLY vertices have {table.shape[1]} values per line, "
                         f"the header declares {len(vertex.properties)}")
    return table


def _parse_table(rows: list[str], delimiter: str | None, name: str, what: str) -> np.ndarray:
    """Parse rows of numbers with numpy's C parser; ragged or non-numeric rows are refused, naming the line."""
    try:
        table = np.loadtxt(rows, delimiter=delimiter, dtype=np.float64, ndmin=2, comments=None)
    except ValueError as exc:
        # numpy's messages count rows inconsistently: find the first bad row ourselves (only on this error path)
        width = len([w for w in rows[0].split(delimiter)])
        for number, row in enumerate(rows, start=1):
            words = row.split(delimiter)
            if len(words) != width or not all(_is_number(word) for word in words):
                shown = row if len(row) <= 60 else row[:57] + "..."
                problem = f"{len(words)} values, expected {width}" if len(words) != width else "not a number"
                raise CloudError(f"{name}: cannot read {what} data row {number} ({problem}): {shown!r}") from exc
        raise CloudError(f"{name}: cannot read {what} data: {str(exc).splitlines()[0]}") from exc
    return table


# --------------------------------------------------------------------------------------------------------- CSV / XYZ

def _text_lines(data: bytes, name: str) -> list[str]:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise CloudError(f"{name}: not a text file (binary or corrupt data)") from exc
    lines = [line.strip() for line in text.splitlines()]
    return [line for line in lines if line and not line.startswith("#")]


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _looks_numeric(line: str, delimiter: str | None) -> bool:
    try:
        [float(word) for word in line.split(delimiter) if word.strip()]
    except ValueError:
        return False
    return True


def _read_csv(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    lines = _text_lines(data, name)
    if not lines:
        raise CloudError(f"{name}: the cloud has no points")
    delimiter = "," if "," in lines[0] else None
    header = None
    if not _looks_numeric(lines[0], delimiter):
        header = [word.strip().strip('"').strip("'").lower() for word in lines[0].split(delimiter)]
        lines = lines[1:]
        if not lines:
            raise CloudError(f"{name}: the cloud has no points (header only)")
    table = _parse_table(lines, delimiter, name, "CSV")
    if header is None:
        return _columns_by_position(table, name, "CSV")
    if len(header) != table.shape[1]:
        raise CloudError(f"{name}: CSV header names {len(header)} columns, the data has {table.shape[1]}")
    missing = [c for c in "xyz" if c not in header]
    if missing:
        raise CloudError(f"{name}: CSV header {','.join(header)!r} has no column {', '.join(missing)}")
    present = [n for n in _NORMAL_NAMES if n in header]
    if present and len(present) != 3:
        raise CloudError(f"{name}: CSV header has {' '.join(present)} but not all of nx ny nz")
    points = table[:, [header.index(c) for c in "xyz"]]
    normals = table[:, [header.index(c) for c in _NORMAL_NAMES]] if present else None
    return points, normals


def _read_xyz(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    lines = _text_lines(data, name)
    if not lines:
        raise CloudError(f"{name}: the cloud has no points")
    return _columns_by_position(_parse_table(lines, None, name, "XYZ"), name, "XYZ")


def _columns_by_position(table: np.ndarray, name: str, what: str) -> tuple[np.ndarray, np.ndarray | None]:
    if table.shape[1] == 3:
        return table, None
    if table.shape[1] == 6:
        return table[:, :3], table[:, 3:]
    raise CloudError(f"{name}: {what} rows have {table.shape[1]} columns; expected 3 (x y z) or 6 (x y z nx ny nz)")


# ----------------------------------------------------------------------------------------------------------- writing

def write_cloud_ply(path: str | os.PathLike, points: np.ndarray, normals: np.ndarray | None = None,
                    binary: bool = True, comments=()) -> None:
    """Write a cloud as PLY, atomically.

    Parameters
    ----------
    path : destination file; written as a temporary file in the same folder and moved into place with ``os.replace``.
    points : (n, 3) float, mm; written as double.
    normals : (n, 3) float or None; written as double ``nx ny nz`` (as given, not normalised).
    binary : True for binary little endian, False for ascii (17 significant digits: reads back bit for bit).
    comments : iterable of str, one header ``comment`` line each (no line breaks).

    Raises
    ------
    CloudError : empty points, NaN or infinite values, zero-length normals; nothing is written then.
    ValueError : wrong shapes, or a comment containing a line break.
    """
    name = str(path)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {points.shape}")
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != points.shape:
            raise ValueError(f"normals must have the shape of points {points.shape}, got {normals.shape}")
    comments = [str(c) for c in comments]
    if any("\n" in c or "\r" in c for c in comments):
        raise ValueError("PLY comments must be single lines")
    # the same checks as on reading, before any file is created: a cloud we would refuse is never written
    _checked_cloud(points, normals, name)

    columns = points if normals is None else np.hstack([points, normals])
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    header += [f"comment {c}" for c in comments]
    header += [f"element vertex {len(points)}"]
    header += [f"property double {p}" for p in ("x", "y", "z") + (_NORMAL_NAMES if normals is not None else ())]
    header += ["end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")

    if binary:
        body = np.ascontiguousarray(columns, dtype="<f8").tobytes()
    else:
        text = io.BytesIO()
        np.savetxt(text, columns, fmt="%.17g")
        body = text.getvalue()
    atomic_write(name, head + body)


# ------------------------------------------------------------------------------------------------------------ extent

def check_extent(points: np.ndarray, bbox_min, bbox_max, tolerance_mm: float, part: str = "part") -> None:
    """Refuse a cloud that does not lie within a part's bounding box (grown by a tolerance).

    A cloud in the machine frame, or in inches or metres, lands far outside the part: catch that before any fit.

    Parameters
    ----------
    points : (n, 3) float, mm, part frame
    bbox_min, bbox_max : (3,) float, mm, the part's axis-aligned bounding box in the part frame
    tolerance_mm : float >= 0, how far outside the box a point may lie (stock allowance, fixture, probe radius)
    part : the part's name, for the message

    Raises
    ------
    CloudError : naming the axis (and all others) where the cloud exceeds the box by more than the tolerance.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must have shape (n, 3) with n >= 1, got {points.shape}")
    bbox_min = np.asarray(bbox_min, dtype=np.float64).reshape(3)
    bbox_max = np.asarray(bbox_max, dtype=np.float64).reshape(3)
    if not (np.all(bbox_max >= bbox_min) and np.isfinite(bbox_min).all() and np.isfinite(bbox_max).all()):
        raise ValueError("bbox_min and bbox_max must be finite with bbox_min <= bbox_max")
    if not np.isfinite(tolerance_mm) or tolerance_mm < 0:
        raise ValueError(f"tolerance_mm must be a finite number >= 0, got {tolerance_mm}")
    _refuse_non_finite(points, "cloud", "coordinates")
    # how far the cloud sticks out of the box on either side, per axis
    excess = np.maximum(np.maximum(bbox_min - points.min(axis=0), points.max(axis=0) - bbox_max), 0.0)
    over = excess > tolerance_mm
    if over.any():
        order = np.argsort(-excess)
        parts = [f"{excess[i]:.1f} mm in {'XYZ'[i]}" for i in order if over[i]]
        extra = f" (and {', '.join(parts[1:])})" if len(parts) > 1 else ""
        raise CloudError(f"cloud extent exceeds the {part} part by {parts[0]}{extra}, more than the "
                         f"{tolerance_mm:g} mm allowed: is it in the part frame, in mm?")
