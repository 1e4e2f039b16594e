"""The two test parts (DESIGN.md §6) as CAD models plus a JSON of their analytic surfaces and features.

Parts
-----
``"nas979"``
    NAS 979 cone frustum on a wedge block, flank milled 5-axis with a flat end mill.
``"slots"``
    Slot block of the equivalent-cutting-force paper: one block, three identical slots milled with no compensation,
    geometric compensation only, and comprehensive (geometric + force) compensation.

Each generator reads like a drawing: ``build_nas979(Nas979Params())`` and ``build_slot_block(SlotBlockParams())``
return a ``cadquery.Workplane`` holding one solid, in the part frame, in mm. ``trueaxis.workpiece.part.write_part(name, out_dir)`` writes
``<name>.step``, ``<name>.stl`` and ``<name>.json`` into ``out_dir`` (atomically: temp file in the same folder, then
``os.replace``).

NAS 979 part frame and dimensions
---------------------------------
Z is normal to the fixture's bottom face (the table), pointing up; the origin is the centre of the cone's base circle;
the cone axis is ``a = (sin t, 0, cos t)`` with t the axis inclination (10 deg), i.e. the axis leans towards +X.
The frustum's height ``height`` (20 mm) is measured **along the cone axis**, from the base plane (through the origin,
normal to a) to the top plane, so the top diameter is ``base_diameter - 2 * height * tan(half_angle)``
(80 - 40 tan 15 deg = 69.282 mm). The cone narrows upwards.

The wedge block lies below the cone base: its top face is the cone's base plane (through the origin, normal to a),
its bottom face is the table plane ``z = z_bottom``, its four sides are vertical (parallel to Z), and its footprint on
the table is a ``block_length_x`` x ``block_width_y`` rectangle (100 x 100 mm) centred under the origin. Because the top
face falls towards +X, the block is thinnest at ``x = +block_length_x / 2``, where it is ``block_min_thickness`` (10 mm)
thick: ``z_bottom = -(block_length_x / 2) tan t - block_min_thickness``. The exact NAS 979 tables were not at hand; every
dimension is a parameter and the JSON records the ones used.

Slot block frame and dimensions
-------------------------------
Origin at the front-left corner of the block's top face; X along the block's length, Y along its width, Z up; the block
occupies ``[0, L] x [0, W] x [-H, 0]``. Three identical slots are laid side by side along +X, ``slot_pitch_x`` apart, in
the order ``none``, ``geometric``, ``comprehensive``. Each slot is the sweep of a flat end mill of diameter
``tool_diameter`` (= slot width, 10 mm) along a polyline tool-centre path at depth ``slot_depth`` (3 mm):
default path (relative to the slot's start) ``(0,0) -> (30,0) -> (50,20) -> (50,50)``: a segment along X, one at
45 deg and one along Y, so cutting moves X alone, X and Y together, and Y alone under load (the paper measured contour
error). Depth 3 mm: the paper's equivalent load is its L16 group 7 (ap = 0.6 mm), so the slot is meant to be cut in
five passes of ``axial_depth_per_pass`` = 0.6 mm; 3 mm of wall lets a CMM probe (1-2 mm ball) take points at mid depth,
clear of the top-edge burr and the floor corner. Full-width slotting (ae = 10 mm) is not group 7's ae = 7 mm; the
compensation applies the equivalent load anyway, as the paper does.

JSON schema (version 1)
-----------------------
::

    {
      "part": "nas979" | "slots", "version": 1, "units": "mm",
      "frame": {"description": str, "origin": [x, y, z], "axes": {"x": [3], "y": [3], "z": [3]}},
      "parameters": {name: value, ...},            # every dimension used (the dataclass fields, plus derived ones)
      "derived": {name: value, ...},               # e.g. top_diameter, z_bottom, volumes
      "source_note": str,
      "surfaces": [surface, ...],
      "features": [feature, ...],
      "stl": {"chord_tolerance_mm": float,          # linear deflection asked of the mesher (absolute, mm)
              "angular_tolerance_rad": float,       # angular deflection asked of the mesher
              "chord_error_bound_mm": float,        # analytic bound r (1 - cos(dphi / 2)) from the mesh actually written:
              "widest_triangle_span_rad": float,    #   dphi = widest angular span of a triangle on a curved face
              "chord_error_bound_note": str, "triangles": int, "format": str}
    }

Surfaces (normals are unit vectors pointing **out of the material**; for slot walls and floors that is into the slot):

- ``{"id", "type": "cone", "base_center": [3], "axis": [3] unit, "half_angle_deg", "base_radius", "top_radius",
  "height_range": [0, h], "apex": [3]}``: points ``base_center + s a + rho u`` with
  ``rho = base_radius - s tan(half_angle)``; ``s`` (height) measured along the axis from the base centre. Material is
  inside (towards the axis).
- ``{"id", "type": "plane", "point": [3], "normal": [3], ...extents}``: extents are ``"center"``/``"radius_range"``
  (annulus in the plane), ``"x_range"``/``"y_range"``/``"z_range"`` (box), or for slot walls
  ``"segment": {"start": [x, y], "end": [x, y]}`` with ``"z_range"``.
- ``{"id", "type": "cylinder", "center": [x, y], "axis": [0, 0, 1], "radius", "z_range", "angle_range_deg": [a0, a1]}``:
  slot ends and outer corners; the wall is concave, so its out-of-material normal points towards the axis
  (``"normal_sense": "towards_axis"``). Angles are measured in the XY plane from +X, counter-clockwise, a0 < a1.

Features:

- nas979: ``{"id": "roundness_h2", "type": "roundness", "surface": "cone", "height": s}`` at three heights (2 mm above
  the base, mid height, 2 mm below the top, measured along the axis), ``{"type": "cone_angle", "surface": "cone",
  "nominal_half_angle_deg", "height_range"}``, ``{"type": "diameter", "surface": "cone", "height", "nominal_diameter"}``
  at the reference height (mid height), and the cone axis ``{"type": "axis_direction", ...}``.
- slots: one ``{"id": "slot_<mode>", "type": "slot", "compensation": "none" | "geometric" | "comprehensive",
  "tool_centre_path": [[x, y, z], ...], "pass_depths": [z, ...], "nominal_width", "nominal_depth",
  "tool_diameter", "walls": [ids], "arcs": [ids], "floor": id}`` per slot. ``tool_centre_path`` is the nominal tool-tip
  path at the floor depth (tool axis +Z); ``pass_depths`` are the tool-tip z of each pass.

Helpers for inspection (pure numpy): ``cone_signed_distance`` and ``cone_surface_points``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Iterable, Sequence

import numpy as np

COMPENSATION_MODES = ("none", "geometric", "comprehensive")
JSON_VERSION = 1

_SOURCE_NOTE_NAS979 = (
    "The exact NAS 979 tables were not at hand. Dimensions follow DESIGN.md section 6 (half apex angle 15 deg, cone "
    "axis inclined 10 deg, base diameter 80 mm, height 20 mm on a wedge block); height is measured along the cone axis. "
    "The wedge block footprint and thickness are this project's choice. Every dimension used is in 'parameters'."
)
_SOURCE_NOTE_SLOTS = (
    "Slot block after 'Comprehensive error measurement and compensation method for equivalent cutting forces' "
    "(Int J Adv Manuf Technol): one block, three identical slots milled with no compensation, geometric compensation "
    "only, and comprehensive compensation; the paper reports mean contour errors 56, 34 and 23 um. The slot shape, size "
    "and depth are not given in the paper's summary at hand; they are this project's choice (a path with X, 45 deg and "
    "Y segments so both axes move under load; depth 3 mm in passes of 0.6 mm = the paper's group 7 ap)."
)


# ----------------------------------------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------------------------------------


def _parse_float(name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"parameter {name}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"parameter {name}: {text!r} is not finite")
    return value


def _parse_path(name: str, text: str) -> tuple[tuple[float, float], ...]:
    """Parse ``"x0,y0;x1,y1;..."`` (mm) into a tuple of (x, y) points."""
    points = []
    for chunk in text.replace(" ", "").split(";"):
        if not chunk:
            continue
        xy = chunk.split(",")
        if len(xy) != 2:
            raise ValueError(f"parameter {name}: point {chunk!r} is not 'x,y' (expected 'x0,y0;x1,y1;...')")
        points.append((_parse_float(name, xy[0]), _parse_float(name, xy[1])))
    return tuple(points)


class _Params:
    """Shared constructors of the parameter dataclasses (frozen; every field a dimension in mm or deg)."""

    _label = "part"

    @classmethod
    def from_overrides(cls, overrides: Iterable[str] = ()):
        """Defaults with ``NAME=VALUE`` strings applied (as given by ``--param NAME=VALUE``).

        Raises ValueError naming the parameter for an unknown name, a missing ``=``, a value that is not a number,
        or a combination that does not make a part.
        """
        types = {f.name: f.type for f in fields(cls)}
        values: dict[str, Any] = {}
        for item in overrides:
            name, sep, text = str(item).partition("=")
            name = name.strip()
            if not sep:
                raise ValueError(f"{cls._label} parameter override {item!r} is not NAME=VALUE")
            if name not in types:
                raise ValueError(
                    f"unknown {cls._label} parameter {name!r}; known: {', '.join(sorted(types))}"
                )
            if "tuple" in str(types[name]):
                values[name] = _parse_path(name, text)
            else:
                values[name] = _parse_float(name, text.strip())
        return cls(**values)

    @classmethod
    def from_kwargs(cls, **overrides: Any):
        """Defaults with keyword overrides; unknown names raise ValueError (not TypeError)."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"unknown {cls._label} parameter(s) {unknown}; known: {', '.join(sorted(known))}")
        return cls(**overrides)

    def as_dict(self) -> dict[str, Any]:
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = [list(p) for p in value] if isinstance(value, tuple) else value
        return out


@dataclass(frozen=True)
class Nas979Params(_Params):
    """NAS 979 cone frustum on its wedge block. Lengths in mm, angles in degrees.

    ``height`` is measured along the cone axis; ``roundness_offset`` places the lower and upper roundness rings that
    far (along the axis) above the base and below the top; ``reference_height`` (along the axis, from the base) is
    where the diameter is evaluated (None: mid height).
    """

    _label = "nas979"

    half_angle_deg: float = 15.0
    axis_inclination_deg: float = 10.0
    base_diameter: float = 80.0
    height: float = 20.0
    block_length_x: float = 100.0
    block_width_y: float = 100.0
    block_min_thickness: float = 10.0
    roundness_offset: float = 2.0
    reference_height: float | None = None

    def __post_init__(self) -> None:
        for name in ("base_diameter", "height", "block_length_x", "block_width_y", "block_min_thickness"):
            if not getattr(self, name) > 0:
                raise ValueError(f"nas979 parameter {name} must be > 0 mm, got {getattr(self, name)}")
        if not 0 < self.half_angle_deg < 90:
            raise ValueError(f"nas979 parameter half_angle_deg must be in (0, 90), got {self.half_angle_deg}")
        if not 0 <= self.axis_inclination_deg < 90:
            raise ValueError(
                f"nas979 parameter axis_inclination_deg must be in [0, 90), got {self.axis_inclination_deg}"
            )
        if self.top_radius <= 0:
            raise ValueError(
                f"nas979: height {self.height} mm at half angle {self.half_angle_deg} deg closes the cone "
                f"(top radius {self.top_radius:.3f} mm); reduce height or half_angle_deg"
            )
        # The base circle must lie on the block's top face: its projection on the table is an ellipse with half axes
        # R cos t (along X) and R (along Y).
        t = math.radians(self.axis_inclination_deg)
        if self.base_radius * math.cos(t) >= self.block_length_x / 2 or self.base_radius >= self.block_width_y / 2:
            raise ValueError(
                f"nas979: the base circle (diameter {self.base_diameter} mm) does not fit on the wedge block's top face "
                f"({self.block_length_x} x {self.block_width_y} mm footprint)"
            )
        if not 0 <= self.roundness_offset < self.height / 2:
            raise ValueError(
                f"nas979 parameter roundness_offset must be in [0, height/2), got {self.roundness_offset}"
            )
        if self.reference_height is not None and not 0 <= self.reference_height <= self.height:
            raise ValueError(
                f"nas979 parameter reference_height must be in [0, height], got {self.reference_height}"
            )

    # --- derived dimensions (mm, unit vectors) ---
    @property
    def base_radius(self) -> float:
        return self.base_diameter / 2

    @property
    def top_radius(self) -> float:
        return self.base_radius - self.height * math.tan(math.radians(self.half_angle_deg))

    @property
    def axis(self) -> np.ndarray:
        """Cone axis a = (sin t, 0, cos t), unit, part frame."""
        t = math.radians(self.axis_inclination_deg)
        return np.array([math.sin(t), 0.0, math.cos(t)])

    @property
    def z_bottom(self) -> float:
        """z of the table plane (the block's bottom face), mm."""
        t = math.radians(self.axis_inclination_deg)
        return -(self.block_length_x / 2) * math.tan(t) - self.block_min_thickness

    @property
    def roundness_heights(self) -> tuple[float, float, float]:
        """Heights along the axis of the three roundness rings: offset above base, mid height, offset below top."""
        return (self.roundness_offset, self.height / 2, self.height - self.roundness_offset)

    @property
    def diameter_reference_height(self) -> float:
        return self.height / 2 if self.reference_height is None else self.reference_height

    def frustum_volume(self) -> float:
        """pi h / 3 (R^2 + R r + r^2), mm^3."""
        R, r, h = self.base_radius, self.top_radius, self.height
        return math.pi * h / 3 * (R * R + R * r + r * r)

    def wedge_volume(self) -> float:
        """Footprint times mean thickness: the top face is linear in x and centred, so the mean is its value at x = 0."""
        return self.block_length_x * self.block_width_y * (-self.z_bottom)

    def cone_surface(self) -> dict:
        """The cone surface dict of the JSON (see the module docstring)."""
        a = self.axis
        apex_height = self.base_radius / math.tan(math.radians(self.half_angle_deg))
        return {
            "id": "cone",
            "type": "cone",
            "base_center": [0.0, 0.0, 0.0],
            "axis": a.tolist(),
            "half_angle_deg": self.half_angle_deg,
            "base_radius": self.base_radius,
            "top_radius": self.top_radius,
            "height_range": [0.0, self.height],
            "apex": (apex_height * a).tolist(),
        }


MAX_SLOT_PASSES = 200  # passes per slot the program generator writes at most


@dataclass(frozen=True)
class SlotBlockParams(_Params):
    """Slot block with three identical slots. Lengths in mm.

    ``slot_path`` is the tool-centre polyline of one slot relative to its start point; slot k (k = 0, 1, 2) starts at
    ``(first_slot_start_x + k * slot_pitch_x, first_slot_start_y)``. Slot width = ``tool_diameter`` (flat end mill,
    full-width slotting); ``axial_depth_per_pass`` splits ``slot_depth`` into passes for the program generator.
    """

    _label = "slots"

    block_length_x: float = 210.0
    block_width_y: float = 80.0
    block_height_z: float = 30.0
    tool_diameter: float = 10.0
    slot_depth: float = 3.0
    axial_depth_per_pass: float = 0.6
    slot_path: tuple[tuple[float, float], ...] = ((0.0, 0.0), (30.0, 0.0), (50.0, 20.0), (50.0, 50.0))
    first_slot_start_x: float = 15.0
    first_slot_start_y: float = 15.0
    slot_pitch_x: float = 65.0

    def __post_init__(self) -> None:
        for name in ("block_length_x", "block_width_y", "block_height_z", "tool_diameter", "slot_depth",
                     "axial_depth_per_pass", "slot_pitch_x"):
            if not getattr(self, name) > 0:
                raise ValueError(f"slots parameter {name} must be > 0 mm, got {getattr(self, name)}")
        if self.slot_depth >= self.block_height_z:
            raise ValueError(f"slots: slot_depth {self.slot_depth} mm cuts through the block ({self.block_height_z} mm)")
        passes = math.ceil(self.slot_depth / self.axial_depth_per_pass - 1e-9)
        if passes > MAX_SLOT_PASSES:  # 0.0001 mm gave 90,000 passes, 720,025 lines in 113 s without a word (QA)
            raise ValueError(f"slots: axial_depth_per_pass {self.axial_depth_per_pass:g} mm makes {passes} passes "
                             f"per slot; at most {MAX_SLOT_PASSES} (a slot is cut in a few passes of tenths of a mm)")
        path = np.asarray(self.slot_path, dtype=float)
        if path.ndim != 2 or path.shape[1] != 2 or len(path) < 2:
            raise ValueError("slots parameter slot_path must hold at least two (x, y) points")
        object.__setattr__(self, "slot_path", tuple((float(x), float(y)) for x, y in path))
        seg = np.diff(path, axis=0)
        lengths = np.linalg.norm(seg, axis=1)
        if np.any(lengths < 1e-6):
            raise ValueError("slots parameter slot_path has a zero-length segment")
        # Inner walls are trimmed by rho tan(phi / 2) at each bend; a segment must be longer than its two trims, and a
        # turn must stay short of a U-turn, or the walls listed in the JSON would not exist.
        rho = self.tool_diameter / 2
        turns = _turn_angles(path)
        if np.any(np.abs(turns) > math.radians(135.0)):
            raise ValueError("slots parameter slot_path turns by more than 135 deg at a vertex")
        trims = rho * np.tan(np.abs(turns) / 2)
        need = np.concatenate([[0.0], trims]) + np.concatenate([trims, [0.0]])
        if np.any(lengths <= need):
            raise ValueError("slots parameter slot_path has a segment shorter than its inner-wall trims at the bends")
        lo = path.min(axis=0) - rho
        hi = path.max(axis=0) + rho
        if self.slot_pitch_x <= hi[0] - lo[0]:
            raise ValueError(
                f"slots: slot_pitch_x {self.slot_pitch_x} mm lets neighbouring slots touch (slot extent "
                f"{hi[0] - lo[0]:.3f} mm along X)"
            )
        x_min = self.first_slot_start_x + lo[0]
        x_max = self.first_slot_start_x + 2 * self.slot_pitch_x + hi[0]
        y_min = self.first_slot_start_y + lo[1]
        y_max = self.first_slot_start_y + hi[1]
        if x_min <= 0 or y_min <= 0 or x_max >= self.block_length_x or y_max >= self.block_width_y:
            raise ValueError(
                f"slots: the three slots span x [{x_min:.3f}, {x_max:.3f}], y [{y_min:.3f}, {y_max:.3f}] mm, "
                f"not inside the {self.block_length_x} x {self.block_width_y} mm block"
            )

    @property
    def slot_width(self) -> float:
        return self.tool_diameter

    def slot_start(self, index: int) -> np.ndarray:
        """(2,) start point of slot ``index`` (0, 1, 2) in the part frame, mm."""
        return np.array([self.first_slot_start_x + index * self.slot_pitch_x, self.first_slot_start_y])

    def tool_centre_path(self, index: int) -> np.ndarray:
        """(P, 3) nominal tool-tip path of slot ``index`` at the floor depth, part frame, mm."""
        xy = np.asarray(self.slot_path) + self.slot_start(index)
        return np.column_stack([xy, np.full(len(xy), -self.slot_depth)])

    def pass_depths(self) -> list[float]:
        """Tool-tip z of each pass (mm), ending exactly at -slot_depth."""
        n = math.ceil(self.slot_depth / self.axial_depth_per_pass - 1e-9)
        return [-self.slot_depth * (k + 1) / n for k in range(n)]

    def swept_area(self) -> float:
        """Area of one slot's outline (the disk of radius rho swept along the path), mm^2.

        2 rho L + pi rho^2 for the straight parts and end caps; at each bend of angle phi the outer side gains a sector
        rho^2 phi / 2 and the inner side's two rectangles overlap in a kite of area rho^2 tan(phi / 2).
        """
        path = np.asarray(self.slot_path)
        rho = self.tool_diameter / 2
        length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
        phi = np.abs(_turn_angles(path))
        return 2 * rho * length + math.pi * rho**2 + float(np.sum(rho**2 * phi / 2 - rho**2 * np.tan(phi / 2)))

    def block_volume(self) -> float:
        """Block minus three slots, mm^3."""
        return self.block_length_x * self.block_width_y * self.block_height_z - 3 * self.slot_depth * self.swept_area()


def _turn_angles(path: np.ndarray) -> np.ndarray:
    """(P-2,) signed turn angle at each interior vertex of a (P, 2) polyline, rad; positive = left turn."""
    seg = np.diff(path, axis=0)
    heading = np.arctan2(seg[:, 1], seg[:, 0])
    return (np.diff(heading) + np.pi) % (2 * np.pi) - np.pi


# ----------------------------------------------------------------------------------------------------------------------
# CAD
# ----------------------------------------------------------------------------------------------------------------------


def build_nas979(params: Nas979Params | None = None):
    """NAS 979 cone frustum on its wedge block, part frame, mm. Returns a ``cadquery.Workplane`` holding one solid."""
    import cadquery as cq

    p = params or Nas979Params()
    tan_t = math.tan(math.radians(p.axis_inclination_deg))
    half_l, half_w = p.block_length_x / 2, p.block_width_y / 2

    # Wedge block: side view (XZ) of the block, extruded symmetrically along Y. Its top edge is the trace of the base
    # plane a . p = 0, i.e. z = -x tan t.
    wedge = (
        cq.Workplane("XZ")
        .polyline([(-half_l, p.z_bottom), (half_l, p.z_bottom), (half_l, -half_l * tan_t), (-half_l, half_l * tan_t)])
        .close()
        .extrude(half_w, both=True)
    )
    # Cone frustum standing on the base plane, along the inclined axis.
    frustum = cq.Solid.makeCone(p.base_radius, p.top_radius, p.height, pnt=cq.Vector(0, 0, 0), dir=cq.Vector(*p.axis))
    return wedge.union(cq.Workplane("XY").add(frustum)).clean()


def build_slot_block(params: SlotBlockParams | None = None):
    """Slot block with three slots, part frame, mm. Returns a ``cadquery.Workplane`` holding one solid.

    Each slot is cut segment by segment: the tool swept along one straight segment is a stadium (``slot2D``) of the
    segment's length plus the tool diameter, centred on the segment; the union of the stadiums is the swept slot.
    """
    import cadquery as cq

    p = params or SlotBlockParams()
    block = cq.Workplane("XY").box(p.block_length_x, p.block_width_y, p.block_height_z, centered=(False, False, False))
    block = block.translate((0, 0, -p.block_height_z))
    for k in range(len(COMPENSATION_MODES)):
        path = p.tool_centre_path(k)[:, :2]
        for start, end in zip(path[:-1], path[1:]):
            mid = (start + end) / 2
            length = float(np.linalg.norm(end - start))
            angle = math.degrees(math.atan2(end[1] - start[1], end[0] - start[0]))
            cutter = (
                cq.Workplane("XY")
                .workplane(offset=-p.slot_depth)
                .center(float(mid[0]), float(mid[1]))
                .slot2D(length + p.tool_diameter, p.tool_diameter, angle)
                .extrude(p.slot_depth + 1.0)  # through the top face
            )
            block = block.cut(cutter)
    return block.clean()


def _on_plane(workplane, part):
    """Place a part (Workplane, part frame) on ``workplane``'s plane; with no workplane, return the part itself."""
    if workplane is None:
        return part
    solid = part.val().moved(workplane.plane.location)
    return workplane.newObject([solid])


def nas979_workplane(workplane=None, /, **overrides):
    """CadQuery convenience / plugin: the NAS 979 part with keyword overrides of ``Nas979Params``.

    Called plainly, returns a new Workplane. Registered as a Workplane method (``cq.Workplane.nas979 = ...``), the part
    frame is placed on the calling workplane's plane and the solid pushed on its stack.
    """
    return _on_plane(workplane, build_nas979(Nas979Params.from_kwargs(**overrides)))


def slot_block_workplane(workplane=None, /, **overrides):
    """CadQuery convenience / plugin: the slot block with keyword overrides of ``SlotBlockParams`` (see nas979_workplane)."""
    return _on_plane(workplane, build_slot_block(SlotBlockParams.from_kwargs(**overrides)))


# ----------------------------------------------------------------------------------------------------------------------
# Analytic surfaces and features (the JSON)
# ----------------------------------------------------------------------------------------------------------------------


def nas979_description(params: Nas979Params | None = None) -> dict:
    """The JSON document of the NAS 979 part, without the ``stl`` entry (see the module docstring)."""
    p = params or Nas979Params()
    a = p.axis
    t = math.radians(p.axis_inclination_deg)
    half_l, half_w = p.block_length_x / 2, p.block_width_y / 2
    side_x = (lambda x: {"z_range": [p.z_bottom, -x * math.tan(t)], "y_range": [-half_w, half_w]})
    surfaces = [
        p.cone_surface(),
        {"id": "cone_top", "type": "plane", "point": (p.height * a).tolist(), "normal": a.tolist(),
         "center": (p.height * a).tolist(), "radius_range": [0.0, p.top_radius]},
        {"id": "block_top", "type": "plane", "point": [0.0, 0.0, 0.0], "normal": a.tolist(),
         "center": [0.0, 0.0, 0.0], "radius_range": [p.base_radius, None],
         "note": "the wedge's top face (the cone's base plane) outside the base circle, clipped by the block sides"},
        {"id": "block_bottom", "type": "plane", "point": [0.0, 0.0, p.z_bottom], "normal": [0.0, 0.0, -1.0],
         "x_range": [-half_l, half_l], "y_range": [-half_w, half_w]},
        {"id": "block_side_xpos", "type": "plane", "point": [half_l, 0.0, 0.0], "normal": [1.0, 0.0, 0.0], **side_x(half_l)},
        {"id": "block_side_xneg", "type": "plane", "point": [-half_l, 0.0, 0.0], "normal": [-1.0, 0.0, 0.0], **side_x(-half_l)},
        {"id": "block_side_ypos", "type": "plane", "point": [0.0, half_w, 0.0], "normal": [0.0, 1.0, 0.0],
         "x_range": [-half_l, half_l], "z_range": [p.z_bottom, half_l * math.tan(t)]},
        {"id": "block_side_yneg", "type": "plane", "point": [0.0, -half_w, 0.0], "normal": [0.0, -1.0, 0.0],
         "x_range": [-half_l, half_l], "z_range": [p.z_bottom, half_l * math.tan(t)]},
    ]
    tan_half = math.tan(math.radians(p.half_angle_deg))
    features = [
        {"id": f"roundness_{name}", "type": "roundness", "surface": "cone", "height": s,
         "nominal_diameter": 2 * (p.base_radius - s * tan_half), "where": where}
        for name, s, where in zip(("low", "mid", "high"), p.roundness_heights,
                                  ("roundness_offset above the base", "mid height", "roundness_offset below the top"))
    ]
    s_ref = p.diameter_reference_height
    features += [
        {"id": "cone_angle", "type": "cone_angle", "surface": "cone", "nominal_half_angle_deg": p.half_angle_deg,
         "height_range": [p.roundness_offset, p.height - p.roundness_offset]},
        {"id": "diameter_ref", "type": "diameter", "surface": "cone", "height": s_ref,
         "nominal_diameter": 2 * (p.base_radius - s_ref * tan_half)},
        {"id": "axis_direction", "type": "axis_direction", "surface": "cone", "nominal_axis": a.tolist(),
         "nominal_inclination_deg": p.axis_inclination_deg},
    ]
    return {
        "part": "nas979",
        "version": JSON_VERSION,
        "units": "mm",
        "frame": {
            "description": "Z normal to the fixture's bottom face (the table), up; origin at the centre of the cone's "
                           "base circle; the cone axis leans towards +X in the XZ plane; heights on the cone are "
                           "measured along its axis from the base centre",
            "origin": [0.0, 0.0, 0.0],
            "axes": {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]},
        },
        "parameters": p.as_dict(),
        "derived": {
            "base_radius": p.base_radius, "top_radius": p.top_radius, "top_diameter": 2 * p.top_radius,
            "cone_axis": a.tolist(), "z_bottom": p.z_bottom,
            "roundness_heights": list(p.roundness_heights), "diameter_reference_height": s_ref,
            "frustum_volume_mm3": p.frustum_volume(), "wedge_volume_mm3": p.wedge_volume(),
            "volume_mm3": p.frustum_volume() + p.wedge_volume(),
        },
        "source_note": _SOURCE_NOTE_NAS979,
        "surfaces": surfaces,
        "features": features,
    }


def _slot_surfaces(p: SlotBlockParams, index: int, mode: str) -> tuple[list[dict], list[str], list[str], str]:
    """Walls (planes with segment extents), arcs (cylinders) and floor of one slot.

    For a segment of unit direction t, the left normal n = (-t_y, t_x). The left wall lies at path + rho n and the
    material is beyond it, so its out-of-material normal is -n; the right wall lies at path - rho n with normal +n.
    At a bend the inner wall is trimmed to where it meets the next segment's inner wall (rho tan(phi/2) short of the
    vertex), the outer wall stops at the vertex normal and an arc of radius rho about the vertex joins the two.
    """
    rho = p.tool_diameter / 2
    path = p.tool_centre_path(index)[:, :2]
    seg = np.diff(path, axis=0)
    t = seg / np.linalg.norm(seg, axis=1, keepdims=True)
    n_left = np.column_stack([-t[:, 1], t[:, 0]])
    turns = _turn_angles(path)
    z_range = [-p.slot_depth, 0.0]
    z_mid = -p.slot_depth / 2
    prefix = f"slot_{mode}"
    surfaces, walls, arcs = [], [], []

    for k in range(len(seg)):
        for side, sign in (("left", 1.0), ("right", -1.0)):
            start = path[k] + sign * rho * n_left[k]
            end = path[k + 1] + sign * rho * n_left[k]
            # Trim the inner side at each bend: at vertex k (start) the turn is turns[k-1], at vertex k+1 turns[k].
            if k > 0 and np.sign(turns[k - 1]) == sign:
                start = start + rho * math.tan(abs(turns[k - 1]) / 2) * t[k]
            if k < len(seg) - 1 and np.sign(turns[k]) == sign:
                end = end - rho * math.tan(abs(turns[k]) / 2) * t[k]
            normal = -sign * n_left[k]
            wall_id = f"{prefix}_seg{k}_{side}"
            walls.append(wall_id)
            surfaces.append({
                "id": wall_id, "type": "plane", "point": [*((start + end) / 2).tolist(), z_mid],
                "normal": [*normal.tolist(), 0.0],
                "segment": {"start": start.tolist(), "end": end.tolist()}, "z_range": z_range,
            })

    def arc(center, from_dir, sweep, arc_id):
        a0 = math.degrees(math.atan2(from_dir[1], from_dir[0]))
        lo, hi = sorted((a0, a0 + math.degrees(sweep)))
        arcs.append(arc_id)
        surfaces.append({
            "id": arc_id, "type": "cylinder", "center": center.tolist(), "axis": [0.0, 0.0, 1.0], "radius": rho,
            "z_range": z_range, "angle_range_deg": [lo, hi], "normal_sense": "towards_axis",
        })

    # End caps: half circles from the right side round the back (start) / front (end).
    arc(path[0], -n_left[0], -math.pi, f"{prefix}_start_cap")
    arc(path[-1], -n_left[-1], math.pi, f"{prefix}_end_cap")
    # Outer corners: on the outside of each bend, from the incoming segment's outer normal to the outgoing one's.
    for k, phi in enumerate(turns):
        outer = -np.sign(phi) * n_left[k]  # outside of a left turn is the right side
        arc(path[k + 1], outer, phi, f"{prefix}_corner{k + 1}")

    floor_id = f"{prefix}_floor"
    surfaces.append({"id": floor_id, "type": "plane", "point": [*path[0].tolist(), -p.slot_depth],
                     "normal": [0.0, 0.0, 1.0], "region": "the slot outline: tool_centre_path swept by a disk of "
                     "radius nominal_width / 2", "slot": prefix})
    return surfaces, walls, arcs, floor_id


def slot_block_description(params: SlotBlockParams | None = None) -> dict:
    """The JSON document of the slot block, without the ``stl`` entry (see the module docstring)."""
    p = params or SlotBlockParams()
    surfaces = [
        {"id": "block_top", "type": "plane", "point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0],
         "x_range": [0.0, p.block_length_x], "y_range": [0.0, p.block_width_y], "note": "outside the slots"},
        {"id": "block_bottom", "type": "plane", "point": [0.0, 0.0, -p.block_height_z], "normal": [0.0, 0.0, -1.0],
         "x_range": [0.0, p.block_length_x], "y_range": [0.0, p.block_width_y]},
    ]
    features = []
    for k, mode in enumerate(COMPENSATION_MODES):
        slot_surfaces, walls, arcs, floor_id = _slot_surfaces(p, k, mode)
        surfaces += slot_surfaces
        features.append({
            "id": f"slot_{mode}", "type": "slot", "compensation": mode, "order_along_x": k,
            "tool_centre_path": p.tool_centre_path(k).tolist(), "pass_depths": p.pass_depths(),
            "nominal_width": p.slot_width, "nominal_depth": p.slot_depth, "tool_diameter": p.tool_diameter,
            "tool": "flat end mill, axis +Z", "walls": walls, "arcs": arcs, "floor": floor_id,
            "evaluate": ["contour_error", "width", "depth"],
        })
    return {
        "part": "slots",
        "version": JSON_VERSION,
        "units": "mm",
        "frame": {
            "description": "origin at the front-left corner of the block's top face; X along the block's length, "
                           "Y along its width, Z up (normal to the table); the block occupies [0, L] x [0, W] x [-H, 0]",
            "origin": [0.0, 0.0, 0.0],
            "axes": {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]},
        },
        "parameters": p.as_dict(),
        "derived": {"slot_width": p.slot_width, "slot_area_mm2": p.swept_area(), "volume_mm3": p.block_volume(),
                    "compensation_order_along_x": list(COMPENSATION_MODES)},
        "source_note": _SOURCE_NOTE_SLOTS,
        "surfaces": surfaces,
        "features": features,
    }


# ----------------------------------------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------------------------------------


def _angular_span(angles: np.ndarray) -> np.ndarray:
    """(T,) largest circular difference among each row of (T, 3) angles, rad (the triangle's span about an axis)."""
    a = np.sort(np.mod(angles, 2 * np.pi), axis=1)
    gaps = np.diff(np.concatenate([a, a[:, :1] + 2 * np.pi], axis=1), axis=1)
    return 2 * np.pi - gaps.max(axis=1)


def _chord_error_bound(triangles: np.ndarray, centre: np.ndarray, axis: np.ndarray, radius: float
                       ) -> tuple[float, float]:
    """Chord error bound of mesh triangles whose vertices lie on a cone or cylinder, mm.

    triangles : (T, 3, 3) vertices, mm. centre, axis : a point on the surface's axis and its unit direction. radius :
    the largest radius of the surface over the triangles. Returns (bound, widest_span): bound = radius (1 - cos(dphi /
    2)) with dphi the widest angular span of a triangle about the axis. Why it bounds: two generatrices at angles
    theta1, theta2 span a secant plane (for a cone they meet at the apex), the surface patch between them is convex,
    so a triangle with its vertices on the patch lies between the secant plane and the surface, no further from the
    surface than the secant's radial sagitta, at most radius (1 - cos((theta2 - theta1) / 2)).
    """
    if len(triangles) == 0:
        return 0.0, 0.0
    u, w = _axis_basis(axis)
    v = triangles - centre
    span = _angular_span(np.arctan2(v @ w, v @ u))
    widest = float(span.max())
    return radius * (1 - math.cos(widest / 2)), widest


# The STL stores float32: at 200 mm one ulp is 1.5e-5 mm, so vertices are matched to surfaces within 1e-4 mm.
_STL_MATCH_MM = 1e-4


def _triangle_normals(triangles: np.ndarray) -> np.ndarray:
    n = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _nas979_chord_bound(vertices: np.ndarray, faces: np.ndarray, cone: dict) -> tuple[float, float]:
    """Chord error bound of the STL on the cone: its lateral triangles (all vertices on the cone, normal not along a)."""
    a = np.asarray(cone["axis"], float)
    on_cone = np.abs(cone_signed_distance(vertices, cone)) < _STL_MATCH_MM
    tri = vertices[faces[np.all(on_cone[faces], axis=1)]]
    tri = tri[np.abs(_triangle_normals(tri) @ a) < 0.99]  # drop the top cap (its vertices lie on the top circle)
    return _chord_error_bound(tri, np.asarray(cone["base_center"], float), a, float(cone["base_radius"]))


def _slots_chord_bound(vertices: np.ndarray, faces: np.ndarray, p: SlotBlockParams) -> tuple[float, float]:
    """Chord error bound of the STL on the slots' arcs (cylinders of radius rho about the path's vertices)."""
    rho = p.tool_diameter / 2
    z = np.array([0.0, 0.0, 1.0])
    tris = vertices[faces]
    vertical = np.abs(_triangle_normals(tris) @ z) < 0.01
    bound, widest = 0.0, 0.0
    for k in range(len(COMPENSATION_MODES)):
        for centre in p.tool_centre_path(k):
            d = np.linalg.norm(tris[:, :, :2] - centre[:2], axis=2)
            on_arc = vertical & np.all(np.abs(d - rho) < _STL_MATCH_MM, axis=1)
            b, s = _chord_error_bound(tris[on_arc], centre, z, rho)
            bound, widest = max(bound, b), max(widest, s)
    return bound, widest


def _axis_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (u, w) with (u, w, axis) right-handed: u is part X projected normal to the axis (Y if X is
    parallel to it). Ring angles are measured from u, right-handed about the axis."""
    ref = np.array([1.0, 0.0, 0.0])
    if abs(axis @ ref) > 0.9:
        ref = np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ axis) * axis
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def _cone_terms(cone: dict) -> tuple[np.ndarray, np.ndarray, float, float]:
    try:
        c = np.asarray(cone["base_center"], dtype=float).reshape(3)
        a = np.asarray(cone["axis"], dtype=float).reshape(3)
        alpha = math.radians(float(cone["half_angle_deg"]))
        radius = float(cone["base_radius"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"not a cone surface dict (needs base_center, axis, half_angle_deg, base_radius): {exc}") from None
    norm = np.linalg.norm(a)
    if not (norm > 0 and 0 < alpha < math.pi / 2 and radius > 0):
        raise ValueError("cone surface: axis must be non-zero, half_angle_deg in (0, 90), base_radius > 0")
    return c, a / norm, alpha, radius


def cone_signed_distance(points: np.ndarray, cone: dict) -> np.ndarray:
    """Exact signed distance from points to the infinite (one-nappe) cone surface, mm.

    points : (N, 3) float, part frame, mm. cone : a ``"type": "cone"`` surface dict of the part JSON.
    Returns (N,) float: positive outside the material (away from the axis, or beyond the apex), negative inside.

    In the meridian half-plane of each point (h along the axis from the base centre, rho >= 0 from the axis) the
    surface is the ray from the apex A = (R / tan alpha, 0) in direction g = (-cos alpha, sin alpha). The nearest
    point is the foot of the perpendicular on that ray, or the apex when the foot would lie beyond it; the mirror ray
    (the far side of the cone) is never nearer for rho >= 0.
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {p.shape}")
    c, a, alpha, radius = _cone_terms(cone)
    v = p - c
    h = v @ a
    rho = np.linalg.norm(v - np.outer(h, a), axis=1)
    h_apex = radius / math.tan(alpha)
    ca, sa = math.cos(alpha), math.sin(alpha)
    along = -(h - h_apex) * ca + rho * sa              # position of the foot along g, from the apex
    across = rho * ca + (h - h_apex) * sa              # signed distance to the line, + away from the axis side
    distance = np.where(along >= 0, np.abs(across), np.hypot(h - h_apex, rho))
    inside = (h < h_apex) & (rho < (h_apex - h) * math.tan(alpha))
    return np.where(inside, -distance, distance)


def cone_surface_points(cone: dict, heights: Sequence[float] | np.ndarray, n_per_ring: int
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Probing rings on the cone: ``n_per_ring`` equally spaced points at each height.

    cone : a ``"type": "cone"`` surface dict. heights : (H,) float, mm along the axis from the base centre.
    Returns points (H * n_per_ring, 3) and unit outward normals (H * n_per_ring, 3), part frame, ring by ring; ring
    angles 2 pi k / n_per_ring from u (part X projected normal to the axis), right-handed about the axis.
    """
    c, a, alpha, radius = _cone_terms(cone)
    s = np.asarray(heights, dtype=float).reshape(-1)
    if int(n_per_ring) < 1:
        raise ValueError("n_per_ring must be >= 1")
    if np.any(s * math.tan(alpha) > radius):
        raise ValueError("a height lies beyond the cone's apex")
    u, w = _axis_basis(a)
    theta = 2 * np.pi * np.arange(int(n_per_ring)) / int(n_per_ring)
    radial = np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * w       # (n, 3)
    ring_radius = radius - s * math.tan(alpha)                               # (H,)
    points = c + s[:, None, None] * a + ring_radius[:, None, None] * radial  # (H, n, 3)
    normals = math.cos(alpha) * radial + math.sin(alpha) * a                 # (n, 3), unit: gradient of the distance
    normals = np.broadcast_to(normals, points.shape)
    return points.reshape(-1, 3), np.ascontiguousarray(normals.reshape(-1, 3))
