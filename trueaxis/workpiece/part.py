"""What a test part is (the ``Part`` protocol), the registry of the parts, the one part loader and the writer.

A part is one object made once at the edge (the CLI, a test) and handed down; nothing below branches on its name.
Each part lives in its own module of this package holding a module-level ``PART`` that satisfies ``Part``
(``nas979.py``: the NAS 979 cone frustum, ``slot_block.py``: the three-slot block); ``parts()`` finds them, so a third
part is one new module here (and, to be cut in the virtual shop, its NC program in ``trueaxis.postproc.programs``).
"""

from __future__ import annotations

import importlib
import json
import os
import pkgutil
from pathlib import Path
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from ..fileio import atomic_path, atomic_write

# Mesher settings for the STL (absolute linear deflection, mm; angular deflection, rad). On the 40 mm base circle a 1 um
# chord error needs n = pi / sqrt(2 * 0.001 / 40) = 444 chords (0.014 rad each). OCCT's mesher steps about 0.01 rad
# along the circles at this angular setting, but its interior cone triangles span up to 0.014 rad, so the bound comes
# out at about 1 um. write_part measures the widest triangle on the mesh it writes and reports the bound in the JSON.
STL_CHORD_TOLERANCE_MM = 1e-3
STL_ANGULAR_TOLERANCE_RAD = 0.02


@runtime_checkable
class Part(Protocol):
    """A test part: its parameters, CAD, analytic description (the part JSON), probing pattern and raw material.

    name : the part's key (the CLI's choice, the JSON's ``"part"``, the stem of the files ``write_part`` writes).
    title : what a report calls it.  default_machine : the fixture machine it is cut on by default.
    params_type : its frozen parameter dataclass (``from_overrides``, ``from_kwargs``, ``as_dict``).
    evaluation : which of the inspection's feature evaluations reads its features (``"cone"``: the cone, its roundness
    sections and diameter; ``"slots"``: width, straightness, parallelism, position and depth per slot; the table
    ``trueaxis.inspect.report.EVALUATIONS``). A part with features of a new kind adds its evaluation there.
    map_view : how the inspection draws its deviation map: ``"3d"`` (a scatter in space) or ``"plan"`` (XY, with the
    slots' tool-centre paths when the JSON has slot features).
    datums : its datum reference frame, primary first: ((label, candidate surface ids, minimum points), ...).
    bestfit_absorbs : the characteristics (tolerance keys of ``trueaxis.inspect.tolerances.CHARACTERISTICS``) that a
    best-fit alignment takes away, each with why: ((key, reason), ...). A best fit moves and turns the cloud onto the
    CAD where its deviations are least, so what it can move is no longer measured against the part's datums (a
    location, an orientation, a size that a move changes); the inspection reports them "not measured" under
    ``--align bestfit``.
    """

    name: str
    title: str
    default_machine: str
    params_type: type
    evaluation: str
    map_view: str
    datums: tuple
    bestfit_absorbs: tuple

    def build(self, params=None) -> Any:
        """CAD: a ``cadquery.Workplane`` holding one solid, part frame, mm."""

    def description(self, params=None) -> dict:
        """The part JSON (frame, parameters, analytic surfaces, features), without its ``stl`` entry."""

    def stl_chord_bound(self, vertices: np.ndarray, faces: np.ndarray, params, description: dict
                        ) -> tuple[float, float, str]:
        """Chord error bound (mm) of a mesh of the part on its curved faces, the widest triangle's angular span (rad)
        and a note saying how the bound was found."""

    def probe_pattern(self, description: dict, n_points: int) -> tuple[np.ndarray, np.ndarray]:
        """About ``n_points`` probe points (N, 3) mm and unit outward normals (N, 3) on the part, part frame."""

    def program_mismatch(self, description: dict, program_text: str) -> str | None:
        """Why a program of this part cut another geometry than ``description`` (from what the program's comments
        say of it), or None when they agree or the program does not say."""

    def material_mask(self, description: dict) -> Callable[[np.ndarray], np.ndarray]:
        """Callable points (P, 3) mm -> (P,) bool: where the raw part has material (the first cut's engagement)."""

    def params_from(self, description: dict):
        """Its parameter dataclass from a part JSON's ``parameters`` (ValueError or KeyError when they do not fit)."""

    def derived_surfaces(self, description: dict) -> list[dict]:
        """Analytic surfaces the JSON does not list but the parameters define (the inspection adds them)."""

    def bbox(self, description: dict) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (min (3,), max (3,)) in the part frame, mm, from the JSON."""

    def mesh(self, description: dict):
        """Its own closed mesh (``trueaxis.workpiece.mesh.CadMesh``, chord error below 0.1 um) from the JSON, or None:
        then the inspection tessellates ``build(params_from(description))`` with OCCT (or reads the STL beside it)."""


def parts() -> dict[str, Part]:
    """Every part of this package: name -> Part, in name order (the modules holding a ``PART``)."""
    found = {}
    for info in sorted(pkgutil.iter_modules([str(Path(__file__).parent)]), key=lambda m: m.name):
        module = importlib.import_module(f"{__package__}.{info.name}")
        part = getattr(module, "PART", None)
        if part is not None:
            if not isinstance(part, Part):
                raise TypeError(f"{module.__name__}.PART does not satisfy the Part protocol")
            found[part.name] = part
    return dict(sorted(found.items()))


def part_names() -> tuple[str, ...]:
    """The parts' names, sorted (the CLI's choices)."""
    return tuple(parts())


def get_part(name: str) -> Part:
    """The part called ``name``; ValueError naming the known ones otherwise."""
    known = parts()
    if name not in known:
        raise ValueError(f"unknown part {name!r}; known: {', '.join(known)}")
    return known[name]


def part_of(description: dict) -> Part:
    """The part a part JSON describes (its ``"part"`` entry)."""
    return get_part(description.get("part"))


def surface(description: dict, sid: str) -> dict:
    """The surface ``sid`` of a part JSON; ValueError when it has none."""
    for s in description["surfaces"]:
        if s["id"] == sid:
            return s
    raise ValueError(f"part JSON has no surface {sid!r}")


def load_part(part: str, part_json=None, part_dir=None) -> dict:
    """The part JSON: from ``part_json`` (path or dict), ``part_dir/<part>.json``, or the part's default parameters.

    ValueError when the file is missing or describes another part."""
    the_part = get_part(part)
    if isinstance(part_json, dict):
        data = part_json
    elif part_json is not None or part_dir is not None:
        path = Path(part_json) if part_json is not None else Path(part_dir) / f"{part}.json"
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ValueError(f"part JSON {path} not found") from None
    else:
        data = the_part.description()
    if data.get("part") != part:
        raise ValueError(f"part JSON is for {data.get('part')!r}, not {part!r}")
    return data


def write_part(
    name: str,
    out_dir: str | os.PathLike,
    params=None,
    *,
    chord_tolerance_mm: float = STL_CHORD_TOLERANCE_MM,
    angular_tolerance_rad: float = STL_ANGULAR_TOLERANCE_RAD,
) -> dict[str, Path]:
    """Write ``out_dir/<name>.step``, ``.stl`` (binary) and ``.json``; create ``out_dir``. Returns {"step", "stl", "json"}.

    name : a part's name (``part_names()``). params : the part's parameter dataclass (None: defaults).
    The STL is meshed with an absolute linear deflection ``chord_tolerance_mm`` and an angular deflection
    ``angular_tolerance_rad``; the JSON's ``stl`` entry states both and the chord error bound of the mesh written.
    """
    import trimesh

    part = get_part(name)
    params = params if params is not None else part.params_type()
    if not isinstance(params, part.params_type):
        raise ValueError(f"part {name!r} takes {part.params_type.__name__}, got {type(params).__name__}")
    solid = part.build(params).val()
    doc = part.description(params)
    if not (chord_tolerance_mm > 0 and angular_tolerance_rad > 0):
        raise ValueError("chord_tolerance_mm and angular_tolerance_rad must be > 0")

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"step": out / f"{name}.step", "stl": out / f"{name}.stl", "json": out / f"{name}.json"}

    import cadquery as cq

    with atomic_path(paths["step"]) as tmp:
        cq.exporters.export(solid, str(tmp), exportType="STEP")

    with atomic_path(paths["stl"]) as stl_tmp:
        # Absolute (not relative) deflection: cadquery's exporter scales the tolerance by edge size by default.
        ok = solid.exportStl(str(stl_tmp), tolerance=chord_tolerance_mm, angularTolerance=angular_tolerance_rad,
                             ascii=False, relative=False)
        if not ok:
            raise OSError(f"could not write STL for part {name!r}")
        mesh = trimesh.load_mesh(str(stl_tmp), file_type="stl")
        vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        bound, dphi, note = part.stl_chord_bound(vertices, faces, params, doc)
        doc["stl"] = {
            "chord_tolerance_mm": chord_tolerance_mm,
            "angular_tolerance_rad": angular_tolerance_rad,
            "chord_error_bound_mm": bound,
            "widest_triangle_span_rad": dphi,
            "chord_error_bound_note": note,
            "triangles": int(len(mesh.faces)),
            "format": "binary STL, part frame, mm",
        }

    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    atomic_write(paths["json"], text)
    return paths
