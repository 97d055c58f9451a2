"""GIS heights (issue 51 §6): the vertical datum and unit a file states are read, what it does not
state is refused with what to add, the sidecar's keys are honoured or refused per format, a missing
geoid grid is named alone, and a barometer ratio no SLAM scale error explains blames the model."""
import json
import re
import warnings

import laspy
import numpy as np
import pytest
from pyproj import CRS, Transformer
from pyproj.transformer import TransformerGroup

from gis.align.scale_check import ScaleCheck
from gis.loaders import load_model
from gis.loaders.heights import HEIGHT_UNITS_M
from gis.model import GisFormatError
from test_gis_loaders import OFFSET, UTM, _model_ecef, _write_dsm

OREGON_FT = "EPSG:2994"  # NAD83(HARN) / Oregon GIC Lambert (international foot), 2D
NAVD88_FT = "EPSG:8228"  # NAVD88 height (ft)


def _write_las(path, crs: str, p: np.ndarray, offsets) -> None:
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.add_crs(CRS.from_user_input(crs))  # a WKT VLR
    hdr.offsets, hdr.scales = offsets, [0.001] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = p.T
    las.write(path)


def _portland_ft(n: int = 400, z_ft: tuple[float, float] = (100.0, 130.0)) -> np.ndarray:
    """Points over 60 × 60 m of Portland, Oregon, in EPSG:2994 feet, heights z_ft."""
    x0, y0 = Transformer.from_crs("EPSG:4326", OREGON_FT, always_xy=True).transform(-122.68, 45.52)
    rng = np.random.default_rng(3)
    return np.array([x0, y0, 0.0]) + rng.uniform([0, 0, z_ft[0]], [200, 200, z_ft[1]], (n, 3))


def _heights_m(m) -> np.ndarray:
    return m.origin.enu_to_geodetic(m.points_enu)[2]


def _sidecar(path, **doc) -> None:
    path.with_name(path.name + ".georef.json").write_text(json.dumps(doc))


def test_us_survey_foot_is_1200_over_3937_metres_as_proj_has_it():
    assert HEIGHT_UNITS_M["ftUS"] == 1200.0 / 3937.0
    assert HEIGHT_UNITS_M["ftUS"] == pytest.approx(CRS.from_epsg(6360).axis_info[0].unit_conversion_factor, rel=1e-15)
    assert HEIGHT_UNITS_M["ft"] == CRS.from_user_input(NAVD88_FT).axis_info[0].unit_conversion_factor == 0.3048


def test_laz_in_feet_with_navd88_feet_heights_stated_loads_in_metres_or_names_the_one_grid(tmp_path):
    """The issue's file, labelled: Oregon feet + NAVD88 feet (EPSG:2994+8228, a compound WKT VLR).
    With the geoid grid installed the heights land in metres above the ellipsoid (NAVD88 lies ~23 m
    above it in Portland, so 100–130 ft → h ≈ 7–17 m); without it the file is refused naming the one
    grid PROJ's best operation needs and how to install it, not every grid of every operation."""
    p = _portland_ft()
    path = tmp_path / "oregon.laz"
    _write_las(path, f"{OREGON_FT}+8228", p, np.floor(p.min(axis=0)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        group = TransformerGroup(f"{OREGON_FT}+8228", "EPSG:4979", always_xy=True, allow_ballpark=False)
    if group.best_available:
        h = _heights_m(load_model(path, sample_spacing_m=0.01))
        expect = group.transformers[0].transform(*p.T)[2]
        np.testing.assert_allclose(np.sort(h), np.sort(expect), atol=0.01)
        assert np.all((h > 0.0) & (h < 25.0)), (h.min(), h.max())
        return
    with pytest.raises(GisFormatError) as e:
        load_model(path)
    msg = str(e.value)
    best = [g.short_name for g in group.unavailable_operations[0].grids if not g.available]
    assert set(re.findall(r"[\w-]+\.tif\b", msg)) == set(best), msg  # the best operation's grid(s) alone
    assert len(best) == 1 and f"pyproj sync --file {best[0]}" in msg and str(path) in msg


def test_laz_without_a_vertical_crs_is_refused_until_its_heights_are_stated(tmp_path):
    """The issue's file as it came: Oregon feet (2D), heights NAVD88 feet, nothing saying so. It was
    read as metres above the ellipsoid (the model ~320 m off); now it is refused naming the sidecar
    and its keys. A sidecar that says "ellipsoid" but not the unit, in a feet CRS, is refused too; a
    vertical CRS in feet whose unit the sidecar contradicts as well."""
    p = _portland_ft()
    path = tmp_path / "oregon.laz"
    _write_las(path, OREGON_FT, p, np.floor(p.min(axis=0)))
    with pytest.raises(GisFormatError) as e:
        load_model(path)
    msg = str(e.value)
    assert str(path) in msg and "vertical datum is not stated" in msg
    assert "oregon.laz.georef.json" in msg and '"vertical"' in msg and '"vertical_unit"' in msg and "EPSG:8228" in msg
    _sidecar(path, vertical="ellipsoid")
    with pytest.raises(GisFormatError, match=r"oregon.laz.georef.json: the heights' unit is not stated and .* is in foot"):
        load_model(path)
    _sidecar(path, vertical=NAVD88_FT, vertical_unit="m")
    with pytest.raises(GisFormatError, match="'vertical_unit' .* contradicts NAVD88 height"):
        load_model(path)
    _sidecar(path, vertical="ellipsoid", vertical_unit="ft")  # stated: ellipsoidal heights in feet
    m = load_model(path, sample_spacing_m=0.01)
    lat, _, h = m.origin.enu_to_geodetic(m.points_enu)
    stored = laspy.read(path)
    np.testing.assert_allclose(np.sort(h), np.sort(np.asarray(stored.z) * 0.3048), atol=1e-4)
    _, lat_e = Transformer.from_crs(OREGON_FT, "EPSG:4326", always_xy=True).transform(stored.x, stored.y)
    np.testing.assert_allclose(np.sort(lat), np.sort(lat_e), atol=1e-8)  # horizontally: the CRS's feet


def test_heights_in_us_survey_feet_on_the_ellipsoid(tmp_path):
    """UTM (metres) with heights in US survey feet, as the sidecar states: h = z · 1200/3937 m, which
    at 10 000–12 000 ft (a mountain site) is 6–7 mm from the international foot's (2 ppm; more than
    the file's 1 mm step)."""
    rng = np.random.default_rng(4)
    p = OFFSET * [1, 1, 0] + rng.uniform([0, 0, 10_000], [50, 50, 12_000], (300, 3))
    path = tmp_path / "ftus.laz"
    _write_las(path, UTM, p, np.floor(p.min(axis=0)))
    _sidecar(path, vertical="ellipsoid", vertical_unit="ftUS")
    h = np.sort(_heights_m(load_model(path, sample_spacing_m=0.01)))
    z = np.sort(np.asarray(laspy.read(path).z))
    np.testing.assert_allclose(h, z * 1200.0 / 3937.0, atol=5e-4)
    assert np.all(np.abs(h - z * 0.3048) > 5e-3)


def test_geotiff_sidecar_offset_is_added_to_its_heights(tmp_path):
    """A DSM whose heights are 150 m below the truth, with ``offset_m`` [0, 0, 150] in its sidecar:
    the offset is honoured (it was ignored, and the model lay 150 m low), as for meshes."""
    plain = load_model(_write_dsm(tmp_path / "dsm.tif"), sample_spacing_m=2.0)
    shifted = _write_dsm(tmp_path / "low.tif")
    _sidecar(shifted, vertical="ellipsoid", offset_m=[0.0, 0.0, 150.0])
    m = load_model(shifted, sample_spacing_m=2.0)
    np.testing.assert_allclose(np.sort(_heights_m(m)), np.sort(_heights_m(plain)) + 150.0, atol=0.01)
    to_utm = Transformer.from_crs("EPSG:4978", UTM, always_xy=True)
    east_m, east_plain_m = to_utm.transform(*_model_ecef(m).T)[0], to_utm.transform(*_model_ecef(plain).T)[0]
    assert abs(np.mean(east_m) - np.mean(east_plain_m)) < 0.5  # (horizontally where it was)


def test_sidecar_keys_are_honoured_or_refused_per_format(tmp_path):
    """An unknown key is refused with the valid ones listed; a key the format carries itself (a LAS
    file's CRS and offsets) is refused saying so; a sidecar beside GeoJSON (RFC 7946 states WGS 84
    and ellipsoidal heights) is refused; a sidecar 'vertical' beside a compound CRS too."""
    dsm = _write_dsm(tmp_path / "dsm.tif")
    _sidecar(dsm, vertical="ellipsoid", datum="NAVD88")
    with pytest.raises(GisFormatError, match=r"dsm.tif.georef.json: key 'datum' is not valid for a GeoTIFF file "
                                             r"\(unknown key\); valid keys: crs, offset_m, vertical, vertical_unit"):
        load_model(dsm)
    rng = np.random.default_rng(5)
    p = OFFSET + rng.uniform(0, 30, (200, 3))
    las = tmp_path / "c.las"
    _write_las(las, UTM, p, OFFSET)
    _sidecar(las, vertical="ellipsoid", offset_m=[0, 0, 10])
    with pytest.raises(GisFormatError, match="key 'offset_m' is not valid for a LAS/LAZ file .*header's own offsets"):
        load_model(las)
    gj = tmp_path / "b.geojson"
    ring = [[8.0, 47.0, 400.0], [8.0001, 47.0, 400.0], [8.0001, 47.0001, 400.0], [8.0, 47.0, 400.0]]
    gj.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"height": 10}, "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    load_model(gj)
    _sidecar(gj, vertical="egm96")
    with pytest.raises(GisFormatError, match="a GeoJSON file takes no georeference sidecar .*RFC 7946"):
        load_model(gj)
    msl = tmp_path / "msl.las"
    _write_las(msl, "EPSG:32632+5773", p, OFFSET)
    _sidecar(msl, vertical="ellipsoid")
    with pytest.raises(GisFormatError, match="the heights' datum and unit are stated already .*EGM96 height.*remove 'vertical'"):
        load_model(msl)


@pytest.mark.parametrize("ratio, suspect", [(1.09, False), (0.55, False), (2.9, True), (-2.0, True), (0.3, True)])
def test_a_barometer_ratio_no_slam_scale_error_explains_blames_the_model_heights(ratio, suspect):
    """A DSM 150 m low under a camera 80 m up reads k ≈ (80 + 150) / 80 ≈ 2.9; one 320 m high, k < 0:
    no SLAM map is that far off in scale, so the message says the model's heights are suspect."""
    chk = ScaleCheck(ratio, ratio - 0.05, ratio + 0.05, 50)
    assert chk.mismatch == (abs(ratio - 1) > 0.2)
    assert ("GIS model's heights or vertical datum are suspect" in chk.describe()) == suspect


def _write_las_geokeys(path, p: np.ndarray, keys: dict[int, int]) -> None:
    """A LAS 1.2 file whose CRS is GeoTIFF keys (UTM 32N, as laspy writes them) plus ``keys``
    (VerticalCSTypeGeoKey 4096, VerticalUnitsGeoKey 4099), which laspy's parse_crs does not read."""
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.add_crs(CRS.from_user_input(UTM))
    directory = next(v for v in hdr.vlrs if isinstance(v, GeoKeyDirectoryVlr))
    for key_id, value in sorted(keys.items()):
        entry = GeoKeyEntryStruct()
        entry.id, entry.tiff_tag_location, entry.count, entry.value_offset = key_id, 0, 1, value
        directory.geo_keys.append(entry)
    directory.geo_keys_header.number_of_keys = len(directory.geo_keys)
    hdr.offsets, hdr.scales = np.floor(p.min(axis=0)), [0.001] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = p.T
    las.write(path)


def test_las_vertical_geokeys_state_the_heights(tmp_path):
    """GeoTIFF keys (LAS 1.2) may state the heights: VerticalCSTypeGeoKey 5773 (EGM96 height) is applied
    as a compound CRS would be; VerticalUnitsGeoKey 9002 (foot) alone states the unit, the sidecar the
    datum, and a sidecar unit contradicting the file's is refused."""
    from gis.geodesy import msl_to_ellipsoid
    rng = np.random.default_rng(6)
    p = OFFSET + rng.uniform([0, 0, 0], [30, 30, 5], (300, 3))
    msl = tmp_path / "msl.las"
    _write_las_geokeys(msl, p, {4096: 5773, 4099: 9001})
    stored = laspy.read(msl)
    lon, lat = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(stored.x, stored.y)
    if TransformerGroup("EPSG:32632+5773", "EPSG:4979", allow_ballpark=False).best_available:
        h = _heights_m(load_model(msl, sample_spacing_m=0.01))
        np.testing.assert_allclose(np.sort(h), np.sort(msl_to_ellipsoid(lat, lon, np.asarray(stored.z))), atol=0.02)
    else:
        with pytest.raises(GisFormatError, match="egm96"):
            load_model(msl)
    feet = tmp_path / "feet.las"
    _write_las_geokeys(feet, p, {4099: 9002})
    with pytest.raises(GisFormatError, match="vertical datum is not stated"):
        load_model(feet)
    _sidecar(feet, vertical="ellipsoid", vertical_unit="m")
    with pytest.raises(GisFormatError, match="'vertical_unit' 'm' contradicts the file's own height unit"):
        load_model(feet)
    _sidecar(feet, vertical="ellipsoid")
    h = _heights_m(load_model(feet, sample_spacing_m=0.01))
    np.testing.assert_allclose(np.sort(h), np.sort(np.asarray(laspy.read(feet).z) * 0.3048), atol=1e-4)
