"""CMM point clouds in and out: PLY (ascii, binary little/big endian), CSV, XYZ, E57 and DMIS output in; PLY (with
the deviations as a scalar field) and CSV out (DESIGN.md §7).

A cloud is in the part frame, in mm. Exact repeats of a point are dropped and counted (they carry no information).
Bad input is refused, never repaired: an empty, unreadable or truncated file, an unknown extension, NaN or infinite
coordinates and normals of zero length each raise :class:`CloudError` with a one-line message naming the file. Writing
is atomic (temporary file in the same folder, then ``os.replace``), so an error leaves nothing half-written behind.

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
from .kernels import csv_rows

__all__ = ["Cloud", "CloudError", "read_cloud", "write_cloud_ply", "write_deviation_ply", "write_deviation_csv",
           "check_extent", "duplicate_points", "repeated_points"]


class CloudError(ValueError):
    """A cloud file or array that cannot be used as a measurement; the message is one line naming the file."""


@dataclass(frozen=True)
class Cloud:
    """A measured point cloud.

    points : (n, 3) float64, mm, part frame
    normals : (n, 3) float64 unit vectors, or None when the file has none
    source : str, the file it was read from
    repeats_dropped : int, the points of the file that repeated an earlier one exactly (same x, y, z), dropped by
        :func:`read_cloud` (they carry no new information, and counted twice they would double the weight of their
        part of the surface in every fit)
    """

    points: np.ndarray
    normals: np.ndarray | None
    source: str
    repeats_dropped: int = 0

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
    """Read a CMM cloud from a PLY, CSV, XYZ, E57 or DMIS output file.

    Parameters
    ----------
    path : file name; the extension (case-insensitive) selects the format:
        ``.ply``: ascii or binary (little or big endian); vertex properties ``x y z`` and optionally ``nx ny nz``
        (case-insensitive: ``X Y Z`` too), of any numeric type; other properties and elements are ignored. Elements
        with list properties (faces) may follow the vertices, not precede them in a binary file.
        ``.csv`` / ``.txt``: one point a line, the fields separated by ``,``, ``;``, tab or whitespace (the first
        data line decides); with ``;``, tab or whitespace a ``,`` inside a number is a decimal comma (``1,25``;
        whitespace is taken when every ``,`` of the line is inside a field such as ``-5,9147``); with ``,``
        between the fields, rows of decimal commas (``1,4240,34,9056,18,9010``) are refused, naming them. An optional
        header line names the columns, case-insensitive, with an optional length unit of the coordinates in brackets,
        parentheses or as a suffix (``X [in]``, ``x_um``: mm, um, cm, m, in; read into mm): ``x y z`` and optionally
        ``nx ny nz`` or ``i j k``; other named columns (a point name, an id, a deviation) are ignored, so the usual
        CMM export ``Name;X;Y;Z;I;J;K`` reads as it is. Without a header the numeric columns of the first row are
        taken in order (3: x y z, 6: x y z nx ny nz) and text columns (a point name) are skipped. Lines starting with
        ``#`` or ``//`` are comments.
        ``.xyz`` / ``.asc``: whitespace-separated ``x y z`` or ``x y z nx ny nz``; a first line ``//X Y Z ...``
        (CloudCompare's ASCII export) is a header naming the columns, read as for CSV.
        ``.e57`` (ASTM E2807, through libE57Format's Python binding pye57): every scan, its pose applied; E57
        stores metres, read into mm; cartesian or spherical; invalid points (the invalid-state field) dropped.
        DMIS output (``.dmo``, ``.dmi``, ``.dms``, ``.dmis``; ANSI/DMIS 105.2): the measured (actual) point
        features ``FA(label)=FEAT/POINT,CART,x,y,z,i,j,k`` in the file's ``UNITS`` (MM, CM, METER, INCH or FEET;
        MM when none is given), with their vectors as normals. Nominal ``F(label)=FEAT/...`` definitions and
        ``PTMEAS`` targets are programmed positions, not measurements, and are never read as points; other actual
        features (circles, planes) are skipped and counted in the error message when no point is found.

    Returns
    -------
    Cloud with points (n, 3) float64 mm and normals (n, 3) float64 normalised to unit length, or None. A point
    that repeats an earlier one exactly (the same x, y, z: a cloud concatenated with itself, an export taken twice)
    is dropped, the first kept, and counted in ``repeats_dropped``: the same cloud given twice gives the same
    figures, and the same identification, as given once.

    Raises
    ------
    CloudError : empty, unreadable or truncated file, unknown extension, NaN or infinite values, zero-length normals.
    """
    path = Path(path)
    name = str(path)
    ext = path.suffix.lower()
    readers = {".ply": _read_ply, ".csv": _read_csv, ".txt": _read_csv, ".xyz": _read_xyz, ".asc": _read_xyz,
               ".e57": None, **{e: _read_dmis for e in _DMIS_EXTENSIONS}}
    if ext not in readers:
        raise CloudError(f"{name}: unknown cloud extension {path.suffix!r} (expected .ply, .csv, .txt, .xyz, .asc, "
                         f".e57 or DMIS {', '.join(_DMIS_EXTENSIONS)})")
    if ext == ".e57":
        points, normals = _read_e57(path, name)
        return _checked_cloud(points, normals, name)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CloudError(f"{name}: cannot read the file ({exc.strerror or exc})") from exc
    if not data.strip():
        raise CloudError(f"{name}: the file is empty")
    points, normals = readers[ext](data, name)
    return _checked_cloud(points, normals, name)


def _checked_cloud(points: np.ndarray, normals: np.ndarray | None, name: str) -> Cloud:
    """Refuse empty clouds, non-finite values and zero normals; return float64 arrays with unit normals, without the
    points that repeat an earlier one exactly (the first of each kept, with its normal; counted in
    ``Cloud.repeats_dropped``)."""
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
    repeated = repeated_points(points)
    if repeated.any():  # a cloud concatenated with itself, an export taken twice: the same figures as once
        points, normals = points[~repeated], None if normals is None else normals[~repeated]
    return Cloud(points=points, normals=normals, source=name, repeats_dropped=int(repeated.sum()))


def _refuse_non_finite(values: np.ndarray, name: str, what: str) -> None:
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        row = ", ".join(f"{v:g}" for v in values[first])
        raise CloudError(f"{name}: {int(bad.sum())} of {len(values)} points have NaN or infinite {what} "
                         f"(first at point {first}, counting from 0: [{row}])")


def repeated_points(points: np.ndarray) -> np.ndarray:
    """(n,) bool: the points of ``points`` ((n, 3) float, finite) that repeat an earlier one exactly (the same x, y,
    z; -0.0 the same as 0.0). The first of each set of equal points is not marked, so ``points[~repeated]`` keeps
    the distinct points in their order; a cloud concatenated with itself three times has its last 2n marked.

    Each row's 64-bit hash sorted (0.03 s at a million points, where ``np.unique(axis=0)`` took 1.7 s); only rows
    next to one with the same hash are compared (a stable sort: the earliest of equal rows comes first), and a hash
    that different rows share (a collision) has its rows compared exactly, so the answer is exact whatever the
    hash."""
    values = np.ascontiguousarray(points, dtype=np.float64)
    repeated = np.zeros(len(values), bool)
    if len(values) < 2:
        return repeated
    key = _row_hash(values.view(np.uint64))
    if not (np.diff(np.sort(key)) == 0).any():  # numpy's sort: several times faster than argsort, no repeats
        return repeated
    order = np.argsort(key, kind="stable")
    ordered = key[order]
    pair = np.flatnonzero(ordered[1:] == ordered[:-1])  # sorted neighbours with the same hash
    same = (values[order[pair]] == values[order[pair + 1]]).all(axis=1)
    collided = np.isin(ordered, ordered[pair[~same]]) if not same.all() else np.zeros(len(values), bool)
    # a hash held by copies of one point only: every row after its first is a repeat (the stable sort keeps the
    # earliest first); the hashes that different points share: their rows compared exactly, earliest first
    plain = pair[~collided[pair]]
    repeated[order[plain + 1]] = True
    if collided.any():
        rows = np.sort(order[collided])
        _, first = np.unique(values[rows] + 0.0, axis=0, return_index=True)  # + 0.0: -0.0 to 0.0
        repeated[rows] = True
        repeated[rows[first]] = False
    return repeated


def duplicate_points(points: np.ndarray) -> int:
    """How many points of ``points`` ((n, 3) float, finite) repeat another one exactly: n minus the number of
    distinct points (:func:`repeated_points`)."""
    return int(repeated_points(points).sum())


_SIGN_BIT = np.uint64(1 << 63)


def _row_hash(bits: np.ndarray) -> np.ndarray:
    """(n,) uint64 hash of each row of ``bits`` ((n, 3) uint64, the bits of float64 coordinates; -0.0 hashed as
    0.0): each column mixed in with MurmurHash3's 64-bit finaliser (arithmetic modulo 2^64). A plain multiply-xor left
    31,000 collisions among a million points rounded to 0.1 mm."""
    key = np.zeros(len(bits), dtype=np.uint64)
    scratch = np.empty_like(key)  # in place: two arrays of n, whatever the cloud's size
    for column in range(bits.shape[1]):
        key ^= bits[:, column]
        key ^= np.multiply(bits[:, column] == _SIGN_BIT, _SIGN_BIT, out=scratch)  # -0.0's bits back to 0.0's
        for multiplier in (0xFF51AFD7ED558CCD, 0xC4CEB9FE1A85EC53, None):
            key ^= np.right_shift(key, np.uint64(33), out=scratch)
            if multiplier is not None:
                key *= np.uint64(multiplier)
    return key


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
    # the property names case-insensitive, as the CSV header's (some exporters write X Y Z, NX NY NZ)
    lower = [n.lower() for n in names]
    missing = [c for c in "xyz" if c not in lower]
    if missing:
        raise CloudError(f"{name}: PLY vertex element has no property {', '.join(missing)} (in any case)")
    if vertex.has_lists:
        raise CloudError(f"{name}: PLY vertex element has list properties, which a point cloud cannot have")
    present = [n for n in _NORMAL_NAMES if n in lower]
    if present and len(present) != 3:
        raise CloudError(f"{name}: PLY vertex element has {' '.join(present)} but not all of nx ny nz")
    wanted = ["x", "y", "z", *present]
    repeated = [c for c in wanted if lower.count(c) > 1]
    if repeated:
        raise CloudError(f"{name}: PLY vertex element has property {repeated[0]} twice (names read in any case: "
                         f"{', '.join(n for n in names if n.lower() == repeated[0])})")
    if vertex.count == 0:
        raise CloudError(f"{name}: the cloud has no points (PLY header declares 0 vertices)")

    if byte_order is None:
        table = _ply_ascii_vertices(body, elements, index, name)
        columns = {c: table[:, lower.index(c)] for c in wanted}
    else:
        table = _ply_binary_vertices(body, elements, index, byte_order, name)
        columns = {c: table[names[lower.index(c)]] for c in wanted}
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


def _parse_table(rows: list[str], delimiter: str | None, name: str, what: str, usecols: list[int] | None = None,
                 width: int | None = None) -> np.ndarray:
    """Parse rows of numbers with numpy's C parser (only the columns ``usecols`` of rows ``width`` fields wide, when
    given); ragged or non-numeric rows are refused, naming the line."""
    try:
        table = np.loadtxt(rows, delimiter=delimiter, dtype=np.float64, ndmin=2, comments=None, usecols=usecols,
                           quotechar='"' if delimiter is not None else None)
        if usecols is not None and width is not None and delimiter is not None:
            # loadtxt reading some columns does not see a row with more fields than the first: count them
            fields = np.fromiter((row.count(delimiter) for row in rows), dtype=np.int64, count=len(rows)) + 1
            if (fields != width).any():
                raise ValueError("ragged rows")
    except ValueError as exc:
        # numpy's messages count rows inconsistently: find the first bad row ourselves (only on this error path)
        width = width or len([w for w in rows[0].split(delimiter)])
        columns = range(width) if usecols is None else usecols
        for number, row in enumerate(rows, start=1):
            words = [w.strip().strip('"') for w in row.split(delimiter)]
            if len(words) != width or not all(_is_number(words[c]) for c in columns):
                shown = row if len(row) <= 60 else row[:57] + "..."
                problem = f"{len(words)} values, expected {width}" if len(words) != width else "not a number"
                raise CloudError(f"{name}: cannot read {what} data row {number} ({problem}): {shown!r}") from exc
        raise CloudError(f"{name}: cannot read {what} data: {str(exc).splitlines()[0]}") from exc
    return table


# --------------------------------------------------------------------------------------------------------- CSV / XYZ

def _text_lines(data: bytes, name: str) -> list[str]:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        try:  # CMM software on Windows writes its exports in the ANSI code page
            text = data.decode("cp1252")
        except UnicodeDecodeError as exc:
            raise CloudError(f"{name}: not a text file (binary or corrupt data)") from exc
    if "\x00" in text:
        raise CloudError(f"{name}: not a text file (binary or corrupt data)")
    lines = [line.strip() for line in text.splitlines()]
    return [line for line in lines if line and not line.startswith(("#", "//"))]


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _csv_delimiter(line: str) -> str | None:
    """The delimiter of a CSV line: ``;`` (European CMM exports, decimal comma), tab, ``,``, else whitespace."""
    for delimiter in (";", "\t", ","):
        if delimiter in line:
            return delimiter
    return None


def _decimal_commas_between_spaces(line: str) -> bool:
    """True for a line of whitespace-separated fields with decimal commas (``39,3006 0,0000 -5,9147``, a European
    CMM text export): every ',' inside a field of the form ``-12,345`` (digits on both sides), at least two such
    fields, and the other fields without a ','. Read with ',' between the fields, such a line has a field with
    whitespace inside a number, so no other reading is possible."""
    fields = line.split()
    with_comma = [w for w in fields if "," in w]
    return len(with_comma) >= 2 and all(re.fullmatch(r"[+-]?\d+,\d+", w) for w in with_comma)


def _split(line: str, delimiter: str | None) -> list[str]:
    return [word.strip().strip('"').strip("'").strip() for word in line.split(delimiter)]


# the header names a CSV column may have (case-insensitive; a unit in brackets after the name is allowed)
_CSV_NAMES = {"x": "x", "y": "y", "z": "z", "nx": "nx", "ny": "ny", "nz": "nz", "i": "nx", "j": "ny", "k": "nz"}


# length units a CSV header may give a coordinate column (in brackets, parentheses, or as a _suffix), in mm
_CSV_UNITS_MM = {"mm": 1.0, "um": 1e-3, "µm": 1e-3, "micron": 1e-3, "cm": 10.0, "m": 1000.0, "in": 25.4,
                 "inch": 25.4, "inches": 25.4, '"': 25.4}


def _column_name(word: str) -> str:
    """'X [mm]' -> 'x', 'x_mm' -> 'x', ' "I" ' -> 'nx'; any other name is kept lower-case (a name or id column,
    ignored)."""
    return _column_name_and_unit(word)[0]


def _column_name_and_unit(word: str) -> tuple[str, str | None]:
    """('x', 'in') for 'X [in]', 'X (in)' or 'x_in'; ('x', None) for 'X'; the unit lower-case as written."""
    word = word.strip().lower()
    match = re.match(r"^(.*?)\s*[\[(]\s*(.*?)\s*[\])]\s*$", word) or \
        re.match(rf"^(.*?)[\s_]+({'|'.join(map(re.escape, _CSV_UNITS_MM))})\s*$", word)
    name, unit = (match.group(1), match.group(2)) if match else (word, None)
    return _CSV_NAMES.get(name, name), unit or None


def _header_scale(words: list[str], name: str) -> float:
    """The factor (mm per unit) the coordinate columns' unit declares: 1 without one; refused when x, y and z declare
    different units or one trueaxis does not know."""
    units = {}
    for word in words:
        column, unit = _column_name_and_unit(word)
        if column in "xyz" and len(column) == 1 and unit is not None:
            units[column] = unit
    if not units:
        return 1.0
    if set(units) != {"x", "y", "z"}:  # a unit on some coordinates only: the others' is not said (mixed, or one unit
        # meant for all): refused, not guessed
        given = ", ".join(f"{c} in {u!r}" for c, u in sorted(units.items()))
        raise CloudError(f"{name}: CSV header gives a unit for some coordinates only ({given}; "
                         f"{', '.join(c for c in 'xyz' if c not in units)} without): give it for x, y and z, or none "
                         "(mm)")
    unknown = sorted({u for u in units.values() if u not in _CSV_UNITS_MM})
    if unknown:
        raise CloudError(f"{name}: CSV header gives the coordinates in {unknown[0]!r}, a unit trueaxis does not know "
                         f"(known: {', '.join(u for u in _CSV_UNITS_MM if u != chr(34))})")
    scales = {_CSV_UNITS_MM[u] for u in units.values()}
    if len(scales) > 1:
        raise CloudError(f"{name}: CSV header gives x, y and z in different units ({', '.join(units.values())})")
    return scales.pop()


def _read_csv(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """CSV as CMM software and spreadsheets write it (see :func:`read_cloud`)."""
    lines = _text_lines(data, name)
    if not lines:
        raise CloudError(f"{name}: the cloud has no points")
    sample = lines[0] if len(lines) == 1 else lines[1]
    delimiter = _csv_delimiter(sample)
    if delimiter == "," and _decimal_commas_between_spaces(sample):
        delimiter = None  # whitespace between the fields, a ',' inside each number: '39,3006 0,0000 -5,9147'
    if delimiter != ",":
        # with ';', tab or whitespace between the fields a ',' can only be a decimal comma (1,25 = 1.25) -- unless a
        # number has a '.' too: then one of them groups digits (1,234.5 or 1.234,5), which is refused, the row named
        _refuse_digit_grouping(lines, name)
        lines = [line.replace(",", ".") for line in lines]
    first = _split(lines[0], delimiter)
    header = None
    if not any(_is_number(word) for word in first):
        header = [_column_name(word) for word in first]
        lines = lines[1:]
        if not lines:
            raise CloudError(f"{name}: the cloud has no points (header only)")
    row = _split(lines[0], delimiter)
    width = len(row)
    if delimiter == "," and (header is None or len(header) != width):
        _refuse_decimal_commas(lines, row, name)
    if header is None:
        # no header: the numeric columns of the first row, in order (x y z or x y z nx ny nz); text columns
        # (a point name or id before the coordinates, as CMM exports have) are skipped
        columns = [k for k, word in enumerate(row) if _is_number(word)]
        if len(columns) not in (3, 6):
            raise CloudError(f"{name}: CSV rows have {len(columns)} numeric columns; expected 3 (x y z) or 6 "
                             f"(x y z nx ny nz), or a header line naming the columns")
        table = _parse_table(lines, delimiter, name, "CSV", columns, width)
        return table[:, :3], (table[:, 3:] if len(columns) == 6 else None)
    if len(header) != width:
        raise CloudError(f"{name}: CSV header names {len(header)} columns, the data has {width}")
    missing = [c for c in "xyz" if c not in header]
    if missing:
        raise CloudError(f"{name}: CSV header {','.join(first)!r} has no column {', '.join(missing)}")
    present = [n for n in _NORMAL_NAMES if n in header]
    if present and len(present) != 3:
        raise CloudError(f"{name}: CSV header has {' '.join(present)} but not all of nx ny nz (or i j k)")
    wanted = ["x", "y", "z"] + (list(_NORMAL_NAMES) if present else [])
    repeated = [c for c in wanted if header.count(c) > 1]
    if repeated:
        raise CloudError(f"{name}: CSV header names column {repeated[0]} twice")
    table = _parse_table(lines, delimiter, name, "CSV", [header.index(c) for c in wanted], width)
    # coordinates in the header's unit (mm when it names none), into mm; normals have none
    return table[:, :3] * _header_scale(first, name), (table[:, 3:] if present else None)


_GROUPED = re.compile(r"[0-9],[0-9]*\.[0-9]|[0-9]\.[0-9]*,[0-9]")


def _refuse_digit_grouping(lines: list[str], name: str) -> None:
    """Refuse numbers with both a ',' and a '.' (``1,234.5``, ``1.234,5``): a thousands separator, which would be
    read as a second decimal mark (the reader had said "not a number" of the row with its commas turned to points)."""
    text = "\n".join(lines)
    if "," not in text:
        return
    hit = _GROUPED.search(text)
    if hit is None:
        return
    k = text.count("\n", 0, hit.start())
    raise CloudError(f"{name}: the row {lines[k][:80]!r} has a number with both ',' and '.': digits "
                     "grouped by a thousands separator, which trueaxis does not read; export the cloud without digit "
                     "grouping (one decimal mark, no thousands separator)")


def _refuse_decimal_commas(lines: list[str], row: list[str], name: str) -> None:
    """Refuse a CSV written with decimal commas and ',' between the fields (``1,4240,34,9056,18,9010``): its numbers
    cannot be told apart, and read as six numbers it was refused as a cloud 9947 mm beyond the part.

    Said only where no other reading is possible: after any leading text fields (a point name), every row has 6 or
    12 fields (3 or 6 numbers split in two), none with a point or an exponent, each pair an integer and the same
    number (at least 2) of digits: a writer's fixed decimals. An integer cloud cannot look like that: its normals'
    components are -1, 0 or 1, one digit. Checked on every row, and only when the first row has that form."""
    lead = next((k for k, word in enumerate(row) if _is_number(word)), len(row))
    numbers = row[lead:]
    if len(numbers) not in (6, 12) or not all(re.fullmatch(r"-?\d+", w) for w in numbers[0::2]):
        return
    digits = len(numbers[1])
    if digits < 2 or not all(re.fullmatch(rf"\d{{{digits}}}", w) for w in numbers[1::2]):
        return
    pair = rf"-?\d+,\d{{{digits}}}"
    form = re.compile(rf"(?:[^,]*,){{{lead}}}{pair}(?:,{pair}){{{len(numbers) // 2 - 1}}}")
    if all(form.fullmatch(line) for line in lines):
        shown = ",".join(row) if len(",".join(row)) <= 60 else ",".join(row)[:57] + "..."
        raise CloudError(f"{name}: the CSV looks written with decimal commas and ',' between the fields "
                         f"({shown!r}: {len(numbers)} fields, each second one {digits} digits, no '.'), which "
                         "cannot be told apart; export with ';' or tab between the fields (a ',' is then read as "
                         "the decimal comma) or with decimal points")


def _read_xyz(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    head = data.lstrip()[:2]
    if head == b"//":
        # CloudCompare's ASCII export names its columns in a '//' first line (//X Y Z deviation_um Nx Ny Nz):
        # read it as a header, so the scalar fields are skipped and the normals found wherever they stand
        first, _, rest = data.lstrip().partition(b"\n")
        return _read_csv(first[2:] + b"\n" + rest, name)
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


# --------------------------------------------------------------------------------------------------------------- DMIS

_DMIS_EXTENSIONS = (".dmo", ".dmi", ".dms", ".dmis")
_DMIS_UNITS_MM = {"MM": 1.0, "CM": 10.0, "METER": 1000.0, "INCH": 25.4, "FEET": 304.8}
_DMIS_ACTUAL = re.compile(r"^FA\s*\(\s*([^)]*?)\s*\)\s*=\s*FEAT\s*/\s*([A-Z]+)\s*(?:,(.*))?$")


def _dmis_statements(text: str):
    """(line number, statement) of a DMIS file: ``$$`` starts a comment, a ``$`` ending a line continues the
    statement on the next (ANSI/DMIS 105.2, 5.1)."""
    pending, start = "", None
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("$$", 1)[0].rstrip()
        if not line.strip() and not pending:
            continue
        if start is None:
            start = number
        if line.endswith("$"):
            pending += line[:-1]
            continue
        yield start, (pending + line).strip()
        pending, start = "", None
    if pending.strip():
        yield start, pending.strip()


def _read_dmis(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Measured points of a DMIS output file (see :func:`read_cloud`)."""
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    scale = 1.0
    rows, with_vector, skipped = [], [], {}
    for number, statement in _dmis_statements(text):
        upper = statement.upper()
        if upper.startswith("UNITS/"):
            unit = upper[6:].split(",")[0].strip()
            if unit not in _DMIS_UNITS_MM:
                raise CloudError(f"{name}:{number}: unknown DMIS length unit {unit!r} (expected "
                                 f"{', '.join(_DMIS_UNITS_MM)})")
            scale = _DMIS_UNITS_MM[unit]
            continue
        match = _DMIS_ACTUAL.match(upper)
        if match is None:
            continue
        label, kind, rest = match.group(1), match.group(2), match.group(3) or ""
        if kind != "POINT":
            skipped[kind] = skipped.get(kind, 0) + 1
            continue
        words = [w.strip() for w in rest.split(",")]
        if not words or words[0] != "CART":
            raise CloudError(f"{name}:{number}: FA({label}) is a {words[0] if words else 'bare'} point; only CART "
                             "(cartesian) measured points are read")
        try:
            values = [float(w) for w in words[1:]]
        except ValueError:
            raise CloudError(f"{name}:{number}: FA({label}): not a number in {statement!r}") from None
        if len(values) not in (3, 6):
            raise CloudError(f"{name}:{number}: FA({label}) has {len(values)} values after CART; expected x,y,z "
                             "or x,y,z,i,j,k")
        rows.append(np.array(values[:3]) * scale)
        with_vector.append(values[3:] if len(values) == 6 else None)
    if not rows:
        others = ", ".join(f"{n} {k}" for k, n in skipped.items())
        raise CloudError(f"{name}: no measured DMIS point FA(label)=FEAT/POINT,CART,... in the file"
                         + (f" (other actual features: {others})" if others else "")
                         + "; nominal F(...) definitions and PTMEAS targets are not measurements")
    points = np.vstack(rows)
    if all(v is not None for v in with_vector):
        return points, np.array(with_vector, dtype=np.float64)
    if any(v is not None for v in with_vector):
        raise CloudError(f"{name}: some measured points have vectors and some do not: refusing to guess normals")
    return points, None


# ---------------------------------------------------------------------------------------------------------------- E57

def _read_e57(path: Path, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Every scan of an E57 file, its pose applied, in mm (E57 stores metres)."""
    try:
        import pye57
    except ImportError as exc:  # a dependency of the project: only a broken install gets here
        raise CloudError(f"{name}: reading E57 needs the Python package pye57 (pip install pye57)") from exc
    if not path.is_file():
        raise CloudError(f"{name}: cannot read the file (No such file or directory)")
    if path.stat().st_size == 0:
        raise CloudError(f"{name}: the file is empty")
    try:
        e57 = pye57.E57(str(path))
    except Exception as exc:  # libE57Format raises its own exception types
        raise CloudError(f"{name}: not a readable E57 file ({str(exc).splitlines()[0] if str(exc) else exc})") from exc
    try:
        scans = []
        for index in range(e57.scan_count):
            scan = e57.read_scan(index, ignore_missing_fields=True, transform=True)
            scans.append(np.column_stack([scan["cartesianX"], scan["cartesianY"], scan["cartesianZ"]]))
    except Exception as exc:
        raise CloudError(f"{name}: cannot read the E57 scans ({str(exc).splitlines()[0] if str(exc) else exc})") \
            from exc
    finally:
        e57.close()
    if not scans:
        raise CloudError(f"{name}: the E57 file has no scans")
    return np.vstack(scans).astype(np.float64) * 1000.0, None


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


def write_deviation_ply(path: str | os.PathLike, points: np.ndarray, deviation_um: np.ndarray,
                        normals: np.ndarray | None = None, comments=()) -> None:
    """Write a cloud with its deviations as a binary little-endian PLY, atomically.

    The deviation is the vertex property ``scalar_deviation_um`` (double): CloudCompare loads a vertex property
    named ``scalar_<name>`` as the scalar field ``<name>`` (it writes its own fields so too), and any PLY reader
    (plyfile, open3d's tensor API, a CMM package) reads it as a named column.

    points : (n, 3) float, mm. deviation_um : (n,) float, um. normals : (n, 3) or None. comments : header lines.
    Raises CloudError / ValueError as :func:`write_cloud_ply`; a NaN deviation too.
    """
    name = str(path)
    points = np.asarray(points, dtype=np.float64)
    deviation_um = np.asarray(deviation_um, dtype=np.float64).reshape(-1)
    if points.ndim != 2 or points.shape[1] != 3 or len(deviation_um) != len(points):
        raise ValueError(f"points (n, 3) and deviation_um (n,) must match, got {points.shape}, {deviation_um.shape}")
    if not np.isfinite(deviation_um).all():
        raise CloudError(f"{name}: {int((~np.isfinite(deviation_um)).sum())} deviations are NaN or infinite")
    _checked_cloud(points, normals, name)
    names = ["x", "y", "z"] + (list(_NORMAL_NAMES) if normals is not None else []) + ["scalar_deviation_um"]
    columns = [points] + ([np.asarray(normals, dtype=np.float64)] if normals is not None else []) \
        + [deviation_um[:, None]]
    header = ["ply", "format binary_little_endian 1.0"] + [f"comment {c}" for c in comments]
    header += [f"element vertex {len(points)}"] + [f"property double {n}" for n in names] + ["end_header"]
    body = np.ascontiguousarray(np.hstack(columns), dtype="<f8")
    atomic_write(name, [("\n".join(header) + "\n").encode("ascii"), body])  # the array written as it is, no copy


def write_deviation_csv(path: str | os.PathLike, points: np.ndarray, deviation_um: np.ndarray,
                        surface=None) -> None:
    """Write one line per point, ``x_mm,y_mm,z_mm,deviation_um[,surface]``, with that header, atomically.

    Coordinates with 6 decimals (1 nm), deviations with 4 (0.1 nm), rounded half to even (the last digit may differ
    by one from C's printf on exact binary halves): what a CMM package or a spreadsheet takes in; :func:`read_cloud`
    reads the points back. surface : the name of each point's reference surface, as (n,) strings or as a pair
    (names (k,), index (n,) int into names); or None.
    """
    points = np.asarray(points, dtype=np.float64)
    deviation_um = np.asarray(deviation_um, dtype=np.float64).reshape(-1)
    if points.ndim != 2 or points.shape[1] != 3 or len(deviation_um) != len(points):
        raise ValueError(f"points (n, 3) and deviation_um (n,) must match, got {points.shape}, {deviation_um.shape}")
    if not (np.isfinite(points).all() and np.isfinite(deviation_um).all()):
        raise CloudError(f"{path}: NaN or infinite values cannot be written")
    n = len(points)
    header = "x_mm,y_mm,z_mm,deviation_um"
    names_table, name_lengths, codes = np.zeros((0, 1), np.uint8), np.zeros(0, np.int64), np.zeros(0, np.int64)
    if surface is not None:
        if isinstance(surface, tuple):
            names, codes = [str(name) for name in surface[0]], np.asarray(surface[1], dtype=np.int64)
        else:
            names, codes = np.unique(np.asarray(surface, dtype=str), return_inverse=True)
        codes = np.ascontiguousarray(codes, dtype=np.int64)
        if codes.shape != (n,) or (n and (codes.min() < 0 or codes.max() >= len(names))):
            raise ValueError(f"surface must name each of the {n} points")
        if any(("," in name or "\n" in name or not name.isascii() or not name) for name in names):
            raise ValueError("surface names must be non-empty ASCII without ',' or line breaks")
        names_table = np.zeros((len(names), max(len(name) for name in names)), dtype=np.uint8)
        name_lengths = np.array([len(name) for name in names], dtype=np.int64)
        for k, name in enumerate(names):
            names_table[k, :len(name)] = np.frombuffer(name.encode("ascii"), dtype=np.uint8)
        header += ",surface"
    decimals = np.array([6, 6, 6, 4], dtype=np.int64)
    scaled = np.round(np.column_stack([points, deviation_um]) * 10.0 ** decimals)
    if np.abs(scaled).max(initial=0.0) >= 2.0 ** 62:
        raise ValueError("value too large for fixed-point output")
    scaled = np.ascontiguousarray(scaled.astype(np.int64))
    # a row's widest form: per number its sign, its digits (at least one before the point) and the point, a comma;
    # the name and the newline
    largest = np.abs(scaled).max(axis=0, initial=0)
    widths = [2 + max(len(str(int(m))), int(d) + 1) for m, d in zip(largest, decimals)]
    out = np.empty(n * (sum(widths) + len(widths) + 1 + names_table.shape[1]) + 1, dtype=np.uint8)
    body = out[:csv_rows(scaled, decimals, codes, names_table, name_lengths, out)]
    atomic_write(str(path), [(header + "\n").encode("ascii"), body])


# ------------------------------------------------------------------------------------------------------------ extent

# The least share of the part's largest extent a cloud must span (``check_extent``): a unit mistake of 10x and more
# falls below it, a measurement of these parts does not.
MIN_SPAN_SHARE = 0.25

def check_extent(points: np.ndarray, bbox_min, bbox_max, tolerance_mm: float, part: str = "part",
                 outliers: float = 0.0) -> None:
    """Refuse a cloud that does not lie within a part's bounding box (grown by a tolerance).

    A cloud in the machine frame, or in inches or metres, lands far outside the part: catch that before any fit.

    Parameters
    ----------
    points : (n, 3) float, mm, part frame
    bbox_min, bbox_max : (3,) float, mm, the part's axis-aligned bounding box in the part frame
    tolerance_mm : float >= 0, how far outside the box a point may lie (stock allowance, fixture, probe radius)
    part : the part's name, for the message
    outliers : the share of the points (0 to 1) that may lie outside the grown box (flyers, which the inspection's
        gate then leaves out of every feature); a cloud in another frame or unit has nearly all of them outside

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
    if not 0.0 <= outliers < 1.0:
        raise ValueError(f"outliers must be a share in [0, 1), got {outliers}")
    outside = np.any((points < bbox_min - tolerance_mm) | (points > bbox_max + tolerance_mm), axis=1)
    # Too small as well: a cloud in cm, inches or metres, read as mm, shrinks by 10, 25.4 or 1000 into a corner of
    # the part, where every point may pass as lying on a face (a slot block's cloud in metres was inspected as
    # 2.15 um RMS, all on its top face, exit 0). A measurement spans most of the part; MIN_SPAN_SHARE is far below
    # any measurement plan of these parts and above a unit's factor.
    span_cloud = float(np.ptp(points, axis=0).max()) if len(points) > 1 else 0.0
    span_part = float((bbox_max - bbox_min).max())
    if span_cloud < MIN_SPAN_SHARE * span_part:
        raise CloudError(f"the cloud spans {span_cloud:.3g} mm where the {part} part spans {span_part:.3g} mm "
                         f"(less than {MIN_SPAN_SHARE:.0%} of it): is it in mm? (in cm, inches or metres it reads 10, "
                         "25.4 or 1000 times too small; give the unit in the file's header)")
    if outside.sum() <= outliers * len(points):
        return
    # how far the cloud sticks out of the box on either side, per axis
    excess = np.maximum(np.maximum(bbox_min - points.min(axis=0), points.max(axis=0) - bbox_max), 0.0)
    over = excess > tolerance_mm
    if over.any():
        order = np.argsort(-excess)
        parts = [f"{excess[i]:.1f} mm in {'XYZ'[i]}" for i in order if over[i]]
        extra = f" (and {', '.join(parts[1:])})" if len(parts) > 1 else ""
        raise CloudError(f"cloud extent exceeds the {part} part by {parts[0]}{extra}, more than the "
                         f"{tolerance_mm:g} mm allowed ({int(outside.sum())} of {len(points)} points outside): is it "
                         f"a cloud of the {part} part, in its frame, in mm? (a cloud is refined within about a mm of "
                         "the part, never found in another frame: bring it there first)")
