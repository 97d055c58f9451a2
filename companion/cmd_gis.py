"""`terraslam gis import|ls|fetch` and `terraslam align-offline` — GIS cache and offline alignment (issue 5)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional, Tuple

import typer

from companion.cli import app, fail

gis_app = typer.Typer(help="GIS model cache: import, list, fetch.", no_args_is_help=True)
app.add_typer(gis_app, name="gis")

_CONFIG = typer.Option(None, "--config", "-c", help="YAML config file (default: built-in defaults)")
_CACHE = typer.Option(None, "--cache-dir", help="GIS cache directory (default: gis.cache_dir from the config)")


def _site_id(site: Optional[str]) -> Optional[str]:
    from gis.config import AUTO_SITE

    if site == AUTO_SITE:
        raise typer.BadParameter(f"{AUTO_SITE!r} is reserved: gis.site: {AUTO_SITE} means the site covering the position")
    return site


def _app_config(config: Optional[Path]):
    from companion.config import ConfigError, load_config

    try:
        return load_config(config)
    except ConfigError as e:
        fail(str(e))


def _gis_config(config: Optional[Path]):
    return _app_config(config).gis


def _cache(config: Optional[Path], cache_dir: Optional[Path]):
    from gis.cache import GisCache

    return GisCache(cache_dir or _gis_config(config).cache_dir)


@gis_app.command("import")
def gis_import(
    path: Path = typer.Argument(..., help="model file (PLY/OBJ/GLB + .georef.json, LAS/LAZ, CityJSON, GeoJSON, OSM .osm.pbf) or 3D Tiles directory"),
    ground_h_msl_m: Optional[float] = typer.Option(None, "--ground-h-msl-m", help="ground height above MSL for footprints without heights (OSM); default gis.footprint_ground_h_msl_m"),
    ground_dem: Optional[Path] = typer.Option(None, "--ground-dem", help="terrain model (GeoTIFF DTM) under footprints without heights, instead of --ground-h-msl-m; default gis.footprint_ground_dem"),
    site: Optional[str] = typer.Option(None, "--site", help="site id (default: file name + hash)", callback=_site_id),
    config: Optional[Path] = _CONFIG,
    cache_dir: Optional[Path] = _CACHE,
) -> None:
    """Load a GIS model file and store it in the cache (a service whose gis.model is this file, with
    the same settings, then maps it without parsing it again)."""
    from gis.loaders import load_model, source_key
    from gis.model import GisFormatError

    cfg = _gis_config(config)
    if ground_h_msl_m is not None and ground_dem is not None:
        fail("give --ground-h-msl-m or --ground-dem, not both")
    ground = cfg.footprint_ground if ground_h_msl_m is None and ground_dem is None else ground_dem or ground_h_msl_m
    try:
        model = load_model(path, cfg.sample_spacing_m, ground)
    except GisFormatError as e:
        fail(str(e))
    site_id = _cache(config, cache_dir).save_model(model, site, source_key=source_key(path, cfg.sample_spacing_m, ground))
    o = model.origin
    typer.echo(f"imported {path} as site {site_id}: {len(model)} points, origin {o.lat0_deg:.6f}, {o.lon0_deg:.6f}, "
               f"h {o.h0_ellipsoid_m:.1f} m (ellipsoid), CRS {model.source_crs}")


def _georef_verdict(evidence, model_sigma_m: float) -> str:
    """What the flights so far say about a cached model's georeference (gis.align.georef)."""
    from gis.align.georef import GeorefCheck

    if evidence is None or evidence.n == 0:
        return "-"
    chk = GeorefCheck(model_sigma_m)
    chk.add_evidence(evidence)
    c = chk.correction()
    if c is None:
        return f"as configured ({evidence.n} registrations)"
    e, n, u = c.offset_enu_m
    return f"off {math.hypot(e, n):.1f} m, up {u:+.1f} m, 1-σ {c.sigma_m:.1f} m ({evidence.n} registrations)"


@gis_app.command("ls")
def gis_ls(
    config: Optional[Path] = _CONFIG,
    cache_dir: Optional[Path] = _CACHE,
    at: Optional[Tuple[float, float]] = typer.Option(None, "--at", metavar="LAT LON",
                                                     help="only the site covering this position (WGS-84 degrees): the one gis.site: auto would fly; exit 1 if none"),
) -> None:
    """List cached GIS models and their transforms."""
    from rich.console import Console
    from rich.table import Table

    from gis.cache import CacheCorrupt

    try:
        cache = _cache(config, cache_dir)
        if at is None:
            entries = cache.entries()
        else:
            if not (-90.0 <= at[0] <= 90.0 and -180.0 <= at[1] <= 180.0):
                fail(f"--at {at[0]} {at[1]} is not LAT LON in degrees (latitude -90..90, longitude -180..180)")
            hit = cache.prefetch(*at)
            if hit is None:
                fail(f"no cached site covers {at[0]:.6f}, {at[1]:.6f}: `terraslam gis fetch --lat {at[0]} --lon {at[1]} "
                     "--source ...` or gis.fetch_sources would get one", code=1)
            entries = [hit]
    except CacheCorrupt as e:
        fail(str(e))
    t = Table("site", "origin lat, lon", "radius m", "points", "CRS", "T_rough", "T_fine", "georeference vs GNSS", "sha256")
    model_sigma_m = _app_config(config).alignment.model_sigma_m
    for e in entries:
        t.add_row(e.site_id, f"{e.origin.lat0_deg:.6f}, {e.origin.lon0_deg:.6f}", f"{e.radius_m:.0f}", str(e.n_points),
                  e.source_crs, _rough_kind(e), "yes" if e.T_fine else "-",
                  _georef_verdict(e.georef, model_sigma_m), e.sha256[:12])
    Console().print(t)
    if not entries:
        typer.echo("(cache is empty)")


def _rough_kind(e) -> str:
    """What a site's T_rough maps: the survey map the service starts in, or only its survey cloud."""
    if e.T_rough is None:
        return "-"
    return "survey map" if str(e.meta.get("rough", {}).get("frame", "")).startswith("survey map") else "cloud frame only"


@gis_app.command("rm")
def gis_rm(
    site: List[str] = typer.Argument(..., help="site id(s), as `terraslam gis ls` lists them"),
    config: Optional[Path] = _CONFIG,
    cache_dir: Optional[Path] = _CACHE,
) -> None:
    """Remove sites from the GIS cache (model, transforms, georeference evidence) and free their files."""
    cache = _cache(config, cache_dir)

    def known(s: str) -> bool:
        try:
            cache.model_file(s)
            return True
        except KeyError:
            return False
    missing = [s for s in site if not known(s)]
    if missing:
        fail(f"no site {', '.join(map(repr, missing))} in the GIS cache ({cache.root}); `terraslam gis ls` lists them")
    for s in site:
        freed = cache.remove(s)
        typer.echo(f"removed site {s}" + (f", {freed / 1e6:.1f} MB freed" if freed else " (its model file is shared or gone)"))


@gis_app.command("fetch")
def gis_fetch(
    lat: float = typer.Option(..., "--lat", help="rough latitude, degrees WGS-84"),
    lon: float = typer.Option(..., "--lon", help="rough longitude, degrees WGS-84"),
    source: List[str] = typer.Option(..., "--source", help="model file, directory or http(s):// 3D Tiles tileset URL (repeatable)"),
    radius_m: Optional[float] = typer.Option(None, "--radius-m", help="fetch radius (default gis.fetch_radius_m)"),
    site: Optional[str] = typer.Option(None, "--site", help="site id (default: file name + hash)", callback=_site_id),
    config: Optional[Path] = _CONFIG,
    cache_dir: Optional[Path] = _CACHE,
) -> None:
    """Obtain the models within a radius of a rough position (TerraSLAM §6) and cache them."""
    from rich.console import Console

    from gis.model import GisFormatError
    from gis.providers import FetchError, fetch_model, providers_for

    cfg = _gis_config(config)
    cache = _cache(config, cache_dir)
    console = Console(stderr=True)
    with console.status("fetching") as status:
        def say(line: str) -> None:
            status.update(line)
            console.log(line)
        providers = providers_for(source, cfg, cache.root / "downloads", progress=say)
        try:
            model = fetch_model(providers, lat, lon, radius_m or cfg.fetch_radius_m, ",".join(source))
        except (FetchError, GisFormatError) as e:
            fail(str(e))
    site_id = cache.save_model(model, site)
    typer.echo(f"fetched {len(model)} points into site {site_id}")


@app.command("align-offline")
def align_offline(
    dataset: Path = typer.Argument(..., help="dataset directory (docs/DATASET.md) of the survey flight"),
    cloud: Optional[Path] = typer.Option(None, "--cloud", help="dense survey cloud (PLY) to compute T_rough for, in its own frame; no survey map is made"),
    stride: int = typer.Option(4, "--stride", min=1, help="use every n-th frame (and every SLAM keyframe) for the COLMAP reconstruction"),
    radius_m: float = typer.Option(250.0, "--radius-m", help="GIS search radius around the rough position"),
    sigma_m: float = typer.Option(1.5, "--sigma-m", min=0.1, max=50.0, help="1-σ (m) of T_rough's position that the service claims when it starts in the survey map (fine-tuning replaces it)"),
    site: Optional[str] = typer.Option(None, "--site", help="site id (default: the dataset name)", callback=_site_id),
    config: Optional[Path] = _CONFIG,
    cache_dir: Optional[Path] = _CACHE,
) -> None:
    """Compute T_rough for a site from a survey (TerraSLAM §4.3) and store it in the GIS cache.

    Without --cloud: our SLAM maps the survey frames (the survey map), COLMAP (pycolmap) SfM
    reconstructs every --stride-th frame and the SLAM keyframes (minutes; the cloud is written to
    DATASET/survey_cloud.ply), T_rough is found on that cloud and carried into the survey map's frame
    through the keyframes' camera centres. The survey map and its T_rough go into the cache: the
    service (gis.site) starts in it and gives fixes without GNSS once it relocalises there.
    """
    import tempfile

    import numpy as np
    import open3d as o3d
    from rich.console import Console

    from companion.dataset import DatasetError, read_dataset
    from gis.align.rough import RoughAlignmentFailed, StartPrior, rough_align
    from gis.loaders import load_model
    from gis.model import GisFormatError

    console = Console(stderr=True)
    app_cfg = _app_config(config)
    cfg = app_cfg.gis
    try:
        ds = read_dataset(dataset)
    except DatasetError as e:
        fail(str(e))
    model, errors = None, []
    for f in ds.gis_files:
        try:
            console.print(f"loading GIS model {f}")
            model = load_model(f, cfg.sample_spacing_m, cfg.footprint_ground)
            break
        except GisFormatError as e:
            errors.append(str(e))
    if model is None:
        fail("no loadable GIS model in the dataset: " + "; ".join(errors or ["site.yaml lists none"]))
    rp = ds.rough_position
    center = model.origin.geodetic_to_enu(rp.lat_deg, rp.lon_deg, rp.h_ellipsoid_m)
    sm = start = None
    if cloud is None:
        from companion.survey import SurveyMappingFailed, map_survey
        from gis.align.survey import SurveyReconstructionFailed, reconstruct_survey

        if ds.camera.is_distorted:
            fail(f"{dataset}: COLMAP here assumes undistorted frames; undistort them or pass --cloud")
        with console.status("SLAM survey map") as status:
            try:
                sm = map_survey(ds.camera, ds.steps(), [p.name for p in ds.frame_paths], app_cfg.slam,
                                progress=lambda k, n: status.update(f"SLAM survey map: frame {k}/{n}"))
            except SurveyMappingFailed as e:
                fail(f"{dataset}: {e}")
        console.print(f"survey map: {len(sm.keyframe_centres)} keyframes, {100 * sm.tracking_ratio:.0f} % of frames tracked")
        names = [p.name for i, p in enumerate(ds.frame_paths) if i % stride == 0 or p.name in sm.keyframe_centres]
        with console.status("COLMAP survey reconstruction") as status:
            try:
                survey = reconstruct_survey(ds.frame_paths[0].parent, names, ds.camera.K, dataset / "colmap",
                                            progress=lambda s: (status.update(s), console.print(s)))
            except SurveyReconstructionFailed as e:
                sm.close()
                fail(f"{dataset}: {e}")
        cloud = dataset / "survey_cloud.ply"
        o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(survey.points)))
        p_slam = survey.points
        first = next(n for n in names if n in survey.camera_centers)  # the survey's start: near the rough position
        start = StartPrior(survey.camera_centers[first], center, rp.sigma_m)
    else:
        p_slam = np.asarray(o3d.io.read_point_cloud(str(cloud)).points)
        if len(p_slam) == 0:
            fail(f"{cloud}: no points could be read")
    try:
        with console.status("offline alignment") as status:
            try:
                res = rough_align(p_slam, model, center, radius_m + rp.sigma_m, start=start,
                                  progress=lambda s: (status.update(s), console.print(s)))
            except RoughAlignmentFailed as e:
                fail(f"{dataset}: {e}")
        cache = _cache(config, cache_dir)
        site_id = cache.save_model(model, site or ds.name)
        meta = {"dataset": str(dataset), "cloud": str(cloud), "error_m": res.error_m, "corner_inliers": res.n_inliers,
                "corner_rmse_m": res.corner_rmse_m, "frame": "the survey cloud's"}
        T_rough = res.T_ecef_slam
        if sm is not None:
            from companion.survey import save_survey_map, survey_alignment
            from gis.align.survey import SurveyRegistrationFailed, register_centres
            from gis.sim3 import compose

            try:
                reg = register_centres(sm.keyframe_centres, survey.camera_centers)
            except SurveyRegistrationFailed as e:
                fail(f"{dataset}: {e}")
            T_rough = compose(res.T_ecef_slam, reg.T_dst_src)
            a = survey_alignment(sm, T_rough, sigma_m)
            with tempfile.TemporaryDirectory(dir=cache.root) as tmp:
                saved = save_survey_map(sm, Path(tmp) / "survey_map.npz", a, site_id)
                cached = cache.save_survey_map(site_id, saved.path)
            meta.update(frame=f"survey map {a.map_id}", survey_map=cached.name, keyframes_registered=reg.n_pairs,
                        centres_rmse_rel=reg.rmse_rel, sigma_m=sigma_m)
            console.print(f"survey map ({saved.n_keyframes} keyframes, {saved.n_points} points, {saved.n_bytes / 1e6:.1f} MB) "
                          f"registered to the reconstruction on {reg.n_pairs} keyframes "
                          f"(residual {100 * reg.rmse_rel:.2f} % of the track)")
        cache.save_transform(site_id, "rough", T_rough, meta)
    finally:
        if sm is not None:
            sm.close()
    typer.echo(f"T_rough stored for site {site_id}: mean point-to-model error {res.error_m:.3f} m, "
               f"scale {T_rough.scale:.5g}, {res.n_inliers} corner inliers"
               + ("; the service starts in its survey map without GNSS" if sm is not None
                  else "; it maps the given cloud's frame only (no survey map)"))
