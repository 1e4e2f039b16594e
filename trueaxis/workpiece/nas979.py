"""The NAS 979 cone frustum on its wedge block (DESIGN.md section 6) as a ``Part``: CAD, JSON, probing pattern.

The geometry (``Nas979Params``, ``build_nas979``, ``nas979_description``) is in ``parts.py`` beside the slot block's,
with the part frame and the JSON schema; this module is what makes it a ``Part``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from .mesh import _unit, nas979_mesh
from .part import surface
from .parts import Nas979Params, _nas979_chord_bound, build_nas979, cone_surface_points, nas979_description


def cone_pattern(part: dict, n_points: int, margin_mm: float = 1.0):
    """Rings on the NAS 979 cone: points (N, 3) mm and unit outward normals (N, 3), part frame."""
    cone = surface(part, "cone")
    h0, h1 = cone["height_range"]
    if not 0 <= 2 * margin_mm < h1 - h0:
        raise ValueError(f"margin_mm {margin_mm} leaves no height to probe on the cone ({h0}-{h1} mm)")
    r_mid = 0.5 * (cone["base_radius"] + cone["top_radius"])
    span = h1 - h0 - 2 * margin_mm
    n_rings = max(1, int(round(math.sqrt(n_points * span / (2 * math.pi * r_mid)))))
    per_ring = max(1, n_points // n_rings)
    heights = np.linspace(h0 + margin_mm, h1 - margin_mm, n_rings) if n_rings > 1 else np.array([0.5 * (h0 + h1)])
    # the part's own sections (roundness, diameter) probed where they are: the ring nearest each, unless an end ring,
    # moved onto it (at 4000 points the rings fell 0.53 mm either side of the mid-height section: never measured, QA)
    moved = np.zeros(heights.size, bool)
    moved[[0, -1]] = True  # the end rings stay where they are: the probed span, the fits' lever, is the same
    for h in sorted({float(f["height"]) for f in part.get("features", []) if f.get("surface") == "cone"
                     and "height" in f and h0 + margin_mm <= float(f["height"]) <= h1 - margin_mm}):
        k = int(np.argmin(np.abs(heights - h)))
        if not moved[k]:  # (the nearest ring only, once: rings far apart stay as they were)
            heights[k], moved[k] = h, True
    return cone_surface_points(cone, np.sort(heights), per_ring)




def cone_title(p: Nas979Params) -> str:
    """The line a NAS 979 program's title names its cone with (``nas979_program``; read back by
    ``read_cone_title``)."""
    return (f"cone: half angle {p.half_angle_deg:g} deg, axis inclined {p.axis_inclination_deg:g} deg, base diameter "
            f"{p.base_diameter:g} mm, height {p.height:g} mm along the axis")


_CONE_TITLE = re.compile(r"^\(cone: half angle (\S+) deg, axis inclined (\S+) deg, base diameter (\S+) mm, "
                         r"height (\S+) mm along the axis\)\s*$", re.MULTILINE)


def read_cone_title(text: str) -> dict | None:
    """The cone a program cuts, from its title comment (``cone_title``): {"half_angle_deg", "axis_inclination_deg",
    "base_diameter", "height"} (deg, mm; as written, 6 significant digits); None when the program has no such line
    (a program from elsewhere)."""
    m = _CONE_TITLE.search(text[:20_000])
    if not m:
        return None
    try:
        values = [float(v) for v in m.groups()]
    except ValueError:
        return None
    return dict(zip(("half_angle_deg", "axis_inclination_deg", "base_diameter", "height"), values))


@dataclass(frozen=True)
class Nas979:
    """The NAS 979 cone frustum, flank milled 5-axis (default machine: the B-C table of nmv1500dcg)."""

    name: str = "nas979"
    title: str = "NAS 979 cone frustum"
    default_machine: str = "nmv1500dcg"
    params_type: type = Nas979Params
    evaluation: str = "cone"
    map_view: str = "3d"
    # A = block bottom, B = a block side normal to X (xneg or xpos), C = a block side normal to Y (yneg or ypos)
    datums: tuple = (("A", ("block_bottom",), 3), ("B", ("block_side_xneg", "block_side_xpos"), 2),
                     ("C", ("block_side_yneg", "block_side_ypos"), 1))
    # a best fit moves the part onto the cone: along its axis (which changes the diameter at a height from the base
    # plane, a uniform size error vanishing with it), across it, and turns it onto the axis
    bestfit_absorbs: tuple = (
        ("diameter_um", "a move along the cone's axis changes its diameter at every height"),
        ("axis_offset_um", "the fit moves the part onto the cone's axis"),
        ("tilt_urad", "the fit turns the part onto the cone's axis"))

    def build(self, params=None):
        return build_nas979(params)

    def description(self, params=None) -> dict:
        return nas979_description(params)

    def stl_chord_bound(self, vertices, faces, params, description):
        """Chord error bound on the cone: its lateral triangles (all vertices on the cone, normal not along a)."""
        bound, dphi = _nas979_chord_bound(vertices, faces, surface(description, "cone"))
        return bound, dphi, ("base_radius (1 - cos(dphi / 2)), dphi the widest angular span about the cone axis of any "
                             "STL triangle on the cone; planes are exact up to float32 rounding (1e-5 mm)")

    def probe_pattern(self, description, n_points):
        return cone_pattern(description, n_points)

    def program_mismatch(self, description, program_text):
        """The cone the program's title names against the description's (``read_cone_title``); None when they agree
        or the program does not say."""
        cut = read_cone_title(program_text)
        if cut is None:
            return None
        said = description.get("parameters", {})
        off = [k for k, v in cut.items() if said.get(k) is None or not math.isclose(float(said[k]), v, rel_tol=1e-5,
                                                                                      abs_tol=1e-6)]
        if not off:
            return None
        return ("the program cuts a cone of " + ", ".join(f"{k} {cut[k]:g}" for k in off) + "; the part's "
                "description gives " + ", ".join(f"{k} {said.get(k)}" for k in off))

    def material_mask(self, description):
        """Material between the cone's base and top planes (the first cut's engagement)."""
        cone = surface(description, "cone")
        a = np.asarray(cone["axis"], float)
        c = np.asarray(cone["base_center"], float)
        h0, h1 = cone["height_range"]
        return lambda p: ((p - c) @ a >= h0) & ((p - c) @ a <= h1)

    def params_from(self, description):
        return Nas979Params.from_kwargs(**description["parameters"])

    def derived_surfaces(self, description):
        return []  # the JSON lists every face

    def bbox(self, description):
        p = description["parameters"]
        cone = next(s for s in description["surfaces"] if s["type"] == "cone")
        a = _unit(cone["axis"])
        t = math.atan2(a[0], a[2])
        half_l, half_w = p["block_length_x"] / 2, p["block_width_y"] / 2
        h = float(cone["height_range"][1])
        r_top = float(cone["top_radius"])
        z_top = max(half_l * math.tan(t), h * a[2] + r_top * abs(math.sin(t)) + 0.0,
                    float(cone["base_radius"]) * abs(math.sin(t)))
        return (np.array([-half_l, -half_w, float(description["derived"]["z_bottom"])]),
                np.array([half_l, half_w, z_top]))

    def mesh(self, description):
        """Meshed from the JSON with numpy (``nas979_mesh``): OCCT needs tens of seconds for the same chord bound."""
        return nas979_mesh(description)


PART = Nas979()
