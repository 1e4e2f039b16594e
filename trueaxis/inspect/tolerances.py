"""Tolerances of a part's features and the feature table of an inspection: nominal, actual, deviation, tolerance,
pass or fail, one row per characteristic (docs/tolerances.md).

Tolerances come from the part JSON (a feature's ``"tolerances"`` object) and from a small TOML file
(``inspect --tolerances FILE``), which wins key by key. Both use the same keys:

- a table (JSON object) per feature id of the part JSON (``roundness_mid``, ``diameter_ref``, ``slot_none``, ...),
  plus ``cone`` for the cone surface as a whole, and ``default`` for every feature that has the characteristic;
- keys are the characteristic with the unit of its limits: size and angle characteristics take ``[lower, upper]``
  limits of the deviation (actual minus nominal), form, orientation and location characteristics take one upper
  limit (their value is >= 0).

A key that no feature of the part has, a feature id the part does not have, or a limit of the wrong shape is refused
with the file and the key: a tolerance that silently applies to nothing would pass a part unchecked.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

__all__ = ["ToleranceError", "CHARACTERISTICS", "load_tolerances", "part_tolerances", "feature_table", "summary"]


class ToleranceError(ValueError):
    """A tolerance file or entry that cannot be used; the message names the file and the key."""


# key -> (kind, feature types it applies to, label); kind "size": [lower, upper] of actual - nominal; "form": upper
CHARACTERISTICS = {
    "roundness_um": ("form", ("roundness",), "roundness (minimum zone)"),
    "half_angle_urad": ("size", ("cone_angle",), "cone half angle"),
    "diameter_um": ("size", ("diameter",), "diameter"),
    "tilt_urad": ("form", ("axis_direction",), "axis tilt from nominal"),
    "form_um": ("form", ("cone",), "cone form (peak-to-valley about the least-squares cone)"),
    "axis_offset_um": ("form", ("cone",), "axis position at the base plane (distance from nominal)"),
    "width_um": ("size", ("slot",), "width"),
    "straightness_um": ("form", ("slot",), "wall straightness (minimum zone, worst wall)"),
    "parallelism_um": ("form", ("slot",), "wall parallelism (worst segment)"),
    "position_um": ("form", ("slot",), "position of the midline (largest |offset|)"),
    "depth_um": ("size", ("slot",), "depth"),
    "contour_um": ("form", ("slot",), "mean contour error"),
}


def _features_by_id(part: dict) -> dict:
    """{feature id: feature type} of a part JSON, with the cone surface as the feature "cone" (type "cone")."""
    features = {f["id"]: f.get("type") for f in part.get("features", []) if "id" in f}
    if any(s.get("type") == "cone" for s in part.get("surfaces", [])):
        features.setdefault("cone", "cone")
    return features


def _limits(value, kind: str, where: str):
    """A checked limit: (lower, upper) floats for size, upper float for form; ToleranceError naming ``where``."""
    if kind == "size":
        if (not isinstance(value, (list, tuple)) or len(value) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise ToleranceError(f"{where}: expected [lower, upper] limits of the deviation, got {value!r}")
        lower, upper = float(value[0]), float(value[1])
        if not (math.isfinite(lower) and math.isfinite(upper) and lower <= upper):
            raise ToleranceError(f"{where}: limits must be finite with lower <= upper, got {value!r}")
        return lower, upper
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ToleranceError(f"{where}: expected one upper limit >= 0 (a form, orientation or location value), "
                             f"got {value!r}")
    return float(value)


def _checked(table: dict, part: dict, source: str) -> dict:
    """{feature id or "default": {key: limits}} checked against the part's features."""
    features = _features_by_id(part)
    out: dict = {}
    for feature, entries in table.items():
        if not isinstance(entries, dict):
            raise ToleranceError(f"{source}: [{feature}] must be a table of characteristic = limits")
        if feature != "default" and feature not in features:
            raise ToleranceError(f"{source}: [{feature}]: the {part.get('part')} part has no feature {feature!r} "
                                 f"(its features: {', '.join(sorted(features))}, or default)")
        for key, value in entries.items():
            if key not in CHARACTERISTICS:
                raise ToleranceError(f"{source}: [{feature}] {key}: unknown characteristic (known: "
                                     f"{', '.join(CHARACTERISTICS)})")
            kind, types, _ = CHARACTERISTICS[key]
            if feature != "default" and features[feature] not in types:
                raise ToleranceError(f"{source}: [{feature}] {key}: a {features[feature]} feature has no {key}")
            if feature == "default" and not any(t in types for t in features.values()):
                raise ToleranceError(f"{source}: [default] {key}: no feature of the {part.get('part')} part has it")
            out.setdefault(feature, {})[key] = _limits(value, kind, f"{source}: [{feature}] {key}")
    return out


def part_tolerances(part: dict) -> dict:
    """Tolerances carried by the part JSON: each feature's ``"tolerances"`` object (and a top-level
    ``"tolerances": {"default": {...}, "cone": {...}}``)."""
    table = {f["id"]: f["tolerances"] for f in part.get("features", []) if "tolerances" in f and "id" in f}
    for feature, entries in (part.get("tolerances") or {}).items():
        table.setdefault(feature, {}).update(entries)
    return _checked(table, part, "part JSON")


def load_tolerances(path, part: dict) -> dict:
    """Read a tolerance TOML for a part and merge it over the part JSON's own tolerances (the file wins per key).

    path : the TOML file (docs/tolerances.md). part : the part JSON dict.
    Returns {feature id or "default": {key: (lower, upper) or upper}}. Raises ToleranceError.
    """
    merged = part_tolerances(part)
    if path is None:
        return merged
    path = Path(path)
    try:
        table = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ToleranceError(f"{path}: cannot read the tolerance file ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ToleranceError(f"{path}: not valid TOML ({exc})") from None
    if not table:
        raise ToleranceError(f"{path}: the tolerance file is empty")
    for feature, entries in _checked(table, part, str(path)).items():
        merged.setdefault(feature, {}).update(entries)
    return merged


def _tolerance_for(tolerances: dict, feature: str, key: str):
    own = tolerances.get(feature, {})
    return own[key] if key in own else tolerances.get("default", {}).get(key)


#: Coverage factor of the expanded uncertainty U = k std a decision takes off (or adds to) the tolerance (ISO 14253-1)
COVERAGE_K = 2.0


def _row(feature, key, label, unit, nominal, actual, deviation, tolerance, note=None, std=None) -> dict:
    """A feature-table row. std : the characteristic's standard uncertainty from its fit (same unit as the deviation),
    or None: with it, conformance is proven only inside the tolerance less U = COVERAGE_K std, non-conformance only
    outside it by more than U; in between the result is "uncertain" (ISO 14253-1's decision rule: 12 points gave a
    half angle of -165 +- 287 urad, judged "pass" against +-200 urad; QA pass)."""
    kind = CHARACTERISTICS[key][0]
    deviation_unit = key.rsplit("_", 1)[1]
    u = 0.0 if std is None or not math.isfinite(std) else COVERAGE_K * float(std)
    if deviation is None:
        result = "not measured"
    elif tolerance is None:
        result = "no tolerance"
    elif kind == "size":
        lo, hi = tolerance
        result = "pass" if lo + u <= deviation <= hi - u else "fail" if (deviation < lo - u or deviation > hi + u) \
            else "uncertain"
    else:
        result = "pass" if deviation + u <= tolerance else "fail" if deviation - u > tolerance else "uncertain"
    row = {"feature": feature, "characteristic": label, "key": key, "unit": unit, "nominal": nominal,
           "actual": actual, "deviation": deviation, "deviation_unit": deviation_unit,
           "tolerance": None if tolerance is None else (
               {"lower": tolerance[0], "upper": tolerance[1]} if kind == "size"
               else {"lower": 0.0, "upper": tolerance}),
           "result": result}
    if std is not None and deviation is not None:
        row["uncertainty"] = {"std": std, "k": COVERAGE_K}
    if note:
        row["note"] = note
    return row


def feature_table(report: dict, part: dict, tolerances: dict, not_measured: dict | None = None) -> list[dict]:
    """One row per characteristic of the inspected features, from the report's evaluated figures.

    Each row: feature (id), characteristic (words), key (the tolerance key), unit (of nominal and actual),
    nominal, actual, deviation and deviation_unit (um or urad; for form values the value itself), tolerance
    ({"lower", "upper"} of the deviation, or None) and result ("pass", "fail", "uncertain", "no tolerance",
    "not measured"; "uncertain": a fit's U = 2 std straddles a limit, see ``_row``), and uncertainty where known.
    not_measured : {key: why}: characteristics the inspection could not measure whatever their figures say (those a
    best-fit alignment takes away): their rows are "not measured", with no actual value, and say why.
    """
    rows: list[dict] = []
    label = {k: v[2] for k, v in CHARACTERISTICS.items()}
    cone = report.get("cone")
    features = {f.get("id"): f for f in part.get("features", [])}
    if "cone_points" in report:
        why = None if cone is not None else report.get("cone_note")  # why the cone was not evaluated
        for fid, feature in features.items():
            kind = feature.get("type")
            if kind == "cone_angle":
                actual = None if cone is None else cone["half_angle_deg"]
                rows.append(_row(fid, "half_angle_urad", label["half_angle_urad"], "deg",
                                 feature.get("nominal_half_angle_deg"), actual,
                                 None if cone is None else cone["half_angle_error_urad"],
                                 _tolerance_for(tolerances, fid, "half_angle_urad"), why,
                                 std=None if cone is None else cone.get("half_angle_std_urad")))
            elif kind == "axis_direction":
                tilt = None if cone is None else cone["axis_tilt_urad"]
                rows.append(_row(fid, "tilt_urad", label["tilt_urad"], "urad", 0.0, tilt, tilt,
                                 _tolerance_for(tolerances, fid, "tilt_urad"), why))
            elif kind == "diameter":
                d = report.get("diameter")
                rows.append(_row(fid, "diameter_um", f"{label['diameter_um']} at h = {feature['height']:g} mm", "mm",
                                 feature.get("nominal_diameter"),
                                 None if d is None or cone is None else d["measured_mm"],
                                 None if d is None or cone is None else d["error_um"],
                                 _tolerance_for(tolerances, fid, "diameter_um"), why))
            elif kind == "roundness":
                ring = next((r for r in report.get("roundness_um", []) if r.get("id") == fid), None)
                value = None if ring is None else ring.get("minimum_zone")
                rows.append(_row(fid, "roundness_um", f"{label['roundness_um']} at h = {feature['height']:g} mm",
                                 "um", 0.0, value, value, _tolerance_for(tolerances, fid, "roundness_um"),
                                 None if ring is None or value is not None else ring.get("note")))
        form_value = None if cone is None else cone.get("form_um")
        rows.append(_row("cone", "form_um", label["form_um"], "um", 0.0, form_value, form_value,
                         _tolerance_for(tolerances, "cone", "form_um"), why))
        offset = None if cone is None else math.hypot(*cone["axis_offset_um"])
        rows.append(_row("cone", "axis_offset_um", label["axis_offset_um"], "um", 0.0, offset, offset,
                         _tolerance_for(tolerances, "cone", "axis_offset_um"), why))
    for slot in report.get("slots", []):
        fid = slot["id"]
        for segment in slot["width"]["segments"]:
            rows.append(_row(fid, "width_um", f"width, segment {segment['segment']}", "mm",
                             slot["width"]["nominal_mm"], segment["width_mm"], segment["width_error_um"],
                             _tolerance_for(tolerances, fid, "width_um"), segment.get("note")))
        # a "worst of" characteristic is known only when each of its members is: else not measured, saying which
        values = list(slot["straightness_um"].values())
        worst = max(values) if values and None not in values else None
        missing = [sid for sid, v in slot["straightness_um"].items() if v is None]
        rows.append(_row(fid, "straightness_um", label["straightness_um"], "um", 0.0, worst, worst,
                         _tolerance_for(tolerances, fid, "straightness_um"),
                         f"walls with fewer than 3 points: {', '.join(missing)}" if missing else None))
        segments = slot["width"]["segments"]
        values = [p["parallelism_um"] for p in slot["parallelism_um"]]
        worst = max(values) if values and len(values) == len(segments) else None
        unmeasured = [str(seg["segment"]) for seg in segments if seg.get("width_mm") is None]
        note = f"segments not measured: {', '.join(unmeasured)}" if unmeasured else None
        rows.append(_row(fid, "parallelism_um", label["parallelism_um"], "um", 0.0, worst, worst,
                         _tolerance_for(tolerances, fid, "parallelism_um"), note))
        worst = slot["position_um"]["max_abs"]
        rows.append(_row(fid, "position_um", label["position_um"], "um", 0.0, worst, worst,
                         _tolerance_for(tolerances, fid, "position_um"), note))
        depth = slot.get("depth")
        rows.append(_row(fid, "depth_um", label["depth_um"], "mm", features.get(fid, {}).get("nominal_depth"),
                         None if depth is None else depth["measured_mm"], None if depth is None else depth["error_um"],
                         _tolerance_for(tolerances, fid, "depth_um")))
        contour = slot.get("mean_contour_error_um")
        rows.append(_row(fid, "contour_um", label["contour_um"], "um", 0.0, contour, contour,
                         _tolerance_for(tolerances, fid, "contour_um"), slot.get("contour_note")))
    for row in rows:
        if row["key"] in (not_measured or {}):
            row.update(actual=None, deviation=None, result="not measured", note=not_measured[row["key"]])
    return rows


def summary(rows: list[dict]) -> dict:
    """Counts of the table's results: {"pass", "fail", "uncertain", "no tolerance", "not measured"}."""
    counts = {"pass": 0, "fail": 0, "uncertain": 0, "no tolerance": 0, "not measured": 0}
    for row in rows:
        counts[row["result"]] += 1
    return counts

