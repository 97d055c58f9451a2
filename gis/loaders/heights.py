"""What a GIS file's coordinates and heights are: its CRS, its heights' vertical datum and unit, and
the ``<file>.georef.json`` sidecar that states what the file does not (issue 51 §6).

Read from the file where it states them (a compound or 3D CRS; a LAS file's vertical GeoKeys), else
from the sidecar; a file that states neither is refused, naming what to add. Never a guess: a LAZ
in a feet CRS whose heights were NAVD88 feet, read as metres above the ellipsoid, put the model
~320 m too high without a word.

Sidecar keys (``SIDECAR_KEYS``: each is honoured for the formats listed, refused for the others;
unknown keys are refused with the valid ones named):

- ``crs``: the CRS of the file's coordinates (pyproj string, e.g. "EPSG:32632"). Meshes: required;
  GeoTIFF: instead of its GeoKeys. LAS/LAZ and CityJSON carry theirs in the file.
- ``offset_m``: [x0, y0, z0] in metres, added to the file's coordinates (meshes, GeoTIFF: its heights
  too): file + offset = coordinates in ``crs`` (converted to the CRS's axis unit where that is feet).
- ``vertical``: the heights' datum where the file's CRS is 2D and it names none: "ellipsoid"
  (WGS 84 ellipsoidal), "egm96" (above the EGM96 geoid, gis.geodesy) or a vertical CRS
  ("EPSG:5703" NAVD88 height, "EPSG:8228" NAVD88 in feet, ...; PROJ converts it, with its geoid grid).
  Refused where the file states its own (a compound or 3D CRS, a LAS VerticalCSTypeGeoKey).
- ``vertical_unit``: "m", "ft" (international foot, 0.3048 m) or "ftUS" (US survey foot, 1200/3937 m):
  the unit of heights on "ellipsoid" / "egm96". Required where the horizontal CRS is not in metres
  (heights in a feet CRS are often feet); with a vertical CRS it may only repeat that CRS's unit.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pyproj import CRS
from pyproj.crs import CompoundCRS
from pyproj.exceptions import CRSError

from gis.loaders.common import _read_json
from gis.model import GisFormatError

#: metres per unit of ``vertical_unit``
HEIGHT_UNITS_M = {"m": 1.0, "ft": 0.3048, "ftUS": 1200.0 / 3937.0}
#: the sidecar keys each format honours (any other key is refused)
SIDECAR_KEYS = {
    "mesh": ("crs", "offset_m", "vertical", "vertical_unit"),
    "GeoTIFF": ("crs", "offset_m", "vertical", "vertical_unit"),
    "LAS/LAZ": ("vertical", "vertical_unit"),
    "CityJSON": ("vertical", "vertical_unit"),
}
#: why a format refuses a key, or a sidecar altogether
_WHY_NOT = {
    ("LAS/LAZ", "crs"): "a LAS/LAZ file carries its CRS in its WKT or GeoTIFF VLR",
    ("LAS/LAZ", "offset_m"): "a LAS/LAZ header's own offsets place its points",
    ("CityJSON", "crs"): "CityJSON names its CRS in metadata.referenceSystem",
    ("CityJSON", "offset_m"): "CityJSON's own 'transform' places its vertices",
}
_NO_SIDECAR = {
    "GeoJSON": "RFC 7946: WGS 84 lon/lat, heights above the WGS 84 ellipsoid; a 'crs' member for projected data",
    "OSM": "OpenStreetMap is WGS 84 lon/lat and carries no ground heights (give the ground instead)",
    "3D Tiles": "3D Tiles are in ECEF (EPSG:4978)",
    "GisModel .npz": "a cached model is in ECEF already",
}
_HOW = ("state the heights' datum in {side}: {{\"vertical\": \"ellipsoid\"}} (WGS 84 ellipsoidal heights), "
        "\"egm96\" (above the EGM96 geoid) or a vertical CRS such as \"EPSG:5703\" (NAVD88 height; \"EPSG:8228\" in feet), "
        "with \"vertical_unit\": \"m\" | \"ft\" | \"ftUS\" where the heights are not in metres; or give the file a "
        "compound CRS (e.g. EPSG:2994+8228)")


@dataclass(frozen=True)
class Georef:
    """How a file's coordinates map to the earth: file (x, y, z) + ``offset`` are coordinates in
    ``crs``. A 2D crs takes z × ``height_unit_m`` as a height in metres on ``vertical`` ("ellipsoid"
    | "egm96"); a 3D or compound crs carries its heights' datum and unit (PROJ converts them)."""

    crs: CRS
    vertical: str = "ellipsoid"
    height_unit_m: float = 1.0
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # in the CRS's axis units


def sidecar_path(path: Path) -> Path:
    return path.with_name(path.name + ".georef.json")


def read_sidecar(path: Path, fmt: str) -> dict:
    """The sidecar's keys ({} without one), each valid for a ``fmt`` file (SIDECAR_KEYS), else
    GisFormatError naming the key, why, and the valid ones."""
    side = sidecar_path(path)
    if not side.is_file():
        return {}
    if fmt not in SIDECAR_KEYS:
        raise GisFormatError(side, f"a {fmt} file takes no georeference sidecar ({_NO_SIDECAR.get(fmt, 'its format states its CRS')}): "
                                   f"remove {side.name}")
    doc = _read_json(side)
    if not isinstance(doc, dict):
        raise GisFormatError(side, "not a JSON object")
    valid = SIDECAR_KEYS[fmt]
    for key in doc:
        if key not in valid:
            why = _WHY_NOT.get((fmt, key), "unknown key")
            raise GisFormatError(side, f"key {key!r} is not valid for a {fmt} file ({why}); valid keys: {', '.join(valid)}")
    return doc


def no_sidecar(path: Path, fmt: str) -> None:
    """Refuse a sidecar beside a file whose format states its CRS and heights itself."""
    read_sidecar(path, fmt)


def georef_of(path: Path, fmt: str, file_crs: CRS | None, doc: dict, file_vertical: CRS | None = None,
              file_height_unit_m: float | None = None) -> Georef:
    """The file's Georef from what it states (``file_crs``; a vertical CRS or height unit it names
    apart from it, as LAS GeoKeys do) and its sidecar ``doc`` (read_sidecar), refusing what neither
    states and what the sidecar contradicts."""
    side = sidecar_path(path)
    try:
        crs = CRS.from_user_input(doc["crs"]) if "crs" in doc else file_crs
    except CRSError as e:
        raise GisFormatError(side, f"bad 'crs' {doc['crs']!r}: {e}") from None
    if crs is None:
        raise GisFormatError(path, f"{fmt} file has no CRS; give it in {side.name}: {{\"crs\": \"EPSG:...\"}}")
    if len(crs.axis_info) >= 3 or file_vertical is not None:
        stated = [k for k in ("vertical", "vertical_unit") if k in doc]
        if stated:
            what = (f"its vertical CRS {file_vertical.name}" if file_vertical is not None else
                    f"the sidecar's 'crs' {crs.name} is 3D" if "crs" in doc else crs.name)
            raise GisFormatError(side, f"the heights' datum and unit are stated already ({what}): remove "
                                       f"{', '.join(map(repr, stated))}")
        if file_vertical is not None:
            crs = CompoundCRS(f"{crs.name} + {file_vertical.name}", [crs, file_vertical])
        return Georef(crs, "ellipsoid", 1.0, _offset(side, doc, crs, crs.axis_info[2].unit_conversion_factor))
    if "vertical" not in doc:
        raise GisFormatError(path, f"the heights' vertical datum is not stated ({crs.name} is 2D and the file names no "
                                   "vertical CRS); " + _HOW.format(side=side.name))
    vertical, unit_m = doc["vertical"], _unit(side, doc, file_height_unit_m)
    if vertical in ("ellipsoid", "egm96"):
        if unit_m is None:
            h_unit = crs.axis_info[0].unit_conversion_factor if crs.is_projected else 1.0
            if h_unit != 1.0:
                raise GisFormatError(side, f"the heights' unit is not stated and {crs.name} is in "
                                           f"{crs.axis_info[0].unit_name}, not metres: add \"vertical_unit\": \"m\" | \"ft\" | \"ftUS\"")
            unit_m = 1.0
        return Georef(crs, vertical, unit_m, _offset(side, doc, crs, unit_m))
    try:
        v = CRS.from_user_input(vertical)
    except (CRSError, TypeError) as e:
        raise GisFormatError(side, f"'vertical' must be \"ellipsoid\", \"egm96\" or a vertical CRS (e.g. \"EPSG:5703\"), "
                                   f"got {vertical!r}: {e}") from None
    if not v.is_vertical:
        raise GisFormatError(side, f"'vertical' {vertical!r} is a {v.type_name}, not a vertical CRS (e.g. \"EPSG:5703\")")
    v_unit = v.axis_info[0].unit_conversion_factor
    if unit_m is not None and not np.isclose(unit_m, v_unit, rtol=1e-9, atol=0.0):
        raise GisFormatError(side, f"'vertical_unit' ({unit_m:.10g} m) contradicts {v.name}, whose heights are in "
                                   f"{v.axis_info[0].unit_name}: remove 'vertical_unit'")
    compound = CompoundCRS(f"{crs.name} + {v.name}", [crs, v])
    return Georef(compound, "ellipsoid", 1.0, _offset(side, doc, compound, v_unit))


def _unit(side: Path, doc: dict, file_height_unit_m: float | None) -> float | None:
    """Metres per height unit as the sidecar's ``vertical_unit`` or the file states it (None: neither)."""
    if "vertical_unit" not in doc:
        return file_height_unit_m
    u = doc["vertical_unit"]
    if u not in HEIGHT_UNITS_M:
        raise GisFormatError(side, f"'vertical_unit' must be one of {', '.join(HEIGHT_UNITS_M)}, got {u!r}")
    if file_height_unit_m is not None and not np.isclose(HEIGHT_UNITS_M[u], file_height_unit_m, rtol=1e-9, atol=0.0):
        raise GisFormatError(side, f"'vertical_unit' {u!r} contradicts the file's own height unit "
                                   f"({file_height_unit_m:.10g} m): remove 'vertical_unit'")
    return HEIGHT_UNITS_M[u]


def _offset(side: Path, doc: dict, crs: CRS, height_unit_m: float) -> np.ndarray:
    """The sidecar's ``offset_m`` (metres) in the CRS's axis units: east/north by the projected CRS's
    unit, up by the heights'; zero without one."""
    if "offset_m" not in doc:
        return np.zeros(3)
    try:
        off = np.asarray(doc["offset_m"], float).reshape(3)
    except (ValueError, TypeError) as e:
        raise GisFormatError(side, f"'offset_m' must be [x0, y0, z0] in metres: {e}") from None
    if not np.all(np.isfinite(off)):
        raise GisFormatError(side, f"'offset_m' must be finite, got {doc['offset_m']!r}")
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    if horizontal.is_projected:
        xy_unit = horizontal.axis_info[0].unit_conversion_factor
    elif off[0] == 0.0 and off[1] == 0.0 or horizontal.is_geocentric:
        xy_unit = 1.0
    else:
        raise GisFormatError(side, f"'offset_m' cannot shift {horizontal.name}'s degrees by metres: give x0 = y0 = 0")
    if horizontal.is_geocentric:
        return off
    return np.array([off[0] / xy_unit, off[1] / xy_unit, off[2] / height_unit_m])
