"""Fetch (TerraSLAM §6 "3D GIS API"): obtain models within a radius of a rough position.

Providers:
- ``LocalProvider(paths)``: model files / 3D Tiles directories on disk; keeps those with a point
  within the radius.
- ``HttpTilesProvider(tileset_url, download_dir, timeout_s)``: a 3D Tiles server over HTTP(S)
  (Cesium ion / Google Photorealistic 3D Tiles style ``tileset.json``). Downloads the tileset,
  the external tilesets and the tile contents that ``gis.loaders.tileset_contents`` selects for
  the sampling spacing (no finer level than that: a Google tileset's leaves within 10 km would be
  terabytes) whose bounding volume comes within the radius, into ``download_dir`` mirroring the
  URL paths (already downloaded files are reused: the cache; only the top tileset is asked for
  again, as a server's session expires, and its mirrored copy serves when that fails), with a
  timeout per request; then loads the local mirror. URIs may be relative or absolute paths; a
  URI's request carries the query of the document that named it (the tileset URL's API key, then
  Google's ``session`` from its root) besides its own, as CesiumJS does: Google's API needs both.
"""
from __future__ import annotations

import json
import logging
import re
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence
from urllib.parse import parse_qsl, unquote, urlencode, urljoin, urlsplit, urlunsplit

import numpy as np
import requests
from requests.adapters import HTTPAdapter
from urllib3.util.retry import Retry

from gis.geodesy import LocalFrame, geodetic_to_ecef
from gis.implicit_tiles import ImplicitTilingError
from gis.loaders import Ground, load_3dtiles, load_model, tileset_contents
from gis.model import GisFormatError, GisModel, merge_models

if TYPE_CHECKING:
    from gis.cache import GisCache
    from gis.config import GisConfig

log = logging.getLogger(__name__)
DOWNLOAD_THREADS = 8  # tile contents fetched at once (CesiumJS allows 18 requests per server)
RETRY = Retry(total=4, backoff_factor=0.5, status_forcelist=(429, 500, 502, 503, 504), allowed_methods=("GET",),
              respect_retry_after_header=True)  # waits 0.5, 1, 2, 4 s (urllib3 2)


class FetchError(RuntimeError):
    """A provider could not obtain a model (network error, timeout, bad response); names the URL."""


@dataclass(frozen=True)
class LocalProvider:
    paths: tuple[Path, ...]
    sample_spacing_m: float = 1.0
    ground: Ground = None  # what building footprints without heights stand on (OSM; gis.loaders.Ground)

    def fetch(self, lat_deg: float, lon_deg: float, radius_m: float) -> list[GisModel]:
        out = []
        for p in self.paths:
            for f in _model_files(Path(p)):
                m = load_model(f, self.sample_spacing_m, self.ground)
                c = m.origin.geodetic_to_enu(lat_deg, lon_deg, m.origin.h0_ellipsoid_m)
                if np.min(np.linalg.norm(m.points_enu[:, :2] - c[:2], axis=1)) <= radius_m:
                    out.append(m)
        return out


def _model_files(p: Path) -> list[Path]:
    if p.is_file() or (p / "tileset.json").is_file():
        return [p]
    if not p.is_dir():
        raise GisFormatError(p, "no such file or directory")
    suffixes = (".ply", ".obj", ".glb", ".gltf", ".las", ".laz", ".json", ".jsonl", ".geojson", ".tif", ".tiff", ".pbf", ".osm")
    return sorted(f for f in p.iterdir() if f.suffix.lower() in suffixes and not f.name.endswith(".georef.json"))


@dataclass(frozen=True)
class HttpTilesProvider:
    tileset_url: str
    download_dir: Path
    timeout_s: float = 30.0
    sample_spacing_m: float = 1.0
    progress: Callable[[str], None] | None = field(default=None, compare=False)  # a line now and then (CLI status)

    def fetch(self, lat_deg: float, lon_deg: float, radius_m: float) -> list[GisModel]:
        centre = geodetic_to_ecef(lat_deg, lon_deg, 0.0)
        urls: dict[Path, str] = {}  # every file this fetch mirrored → its URL
        tiles: list[str] = []  # content URLs, downloaded after the walk, several at a time
        say = self.progress or (lambda line: None)
        name = _redacted(self.tileset_url.split("?")[0])
        with requests.Session() as http:  # one connection pool: keep-alive across hundreds of small tiles
            # a busy or flaky server (429, 5xx, dropped connections) is asked again, backing off, before the fetch fails
            http.mount("http://", HTTPAdapter(max_retries=RETRY, pool_maxsize=DOWNLOAD_THREADS))
            http.mount("https://", HTTPAdapter(max_retries=RETRY, pool_maxsize=DOWNLOAD_THREADS))
            say(f"{name}: reading tilesets")
            local = self._download(http, self.tileset_url, np.eye(4), "REPLACE", centre, radius_m, 0, urls, tiles)
            new, done = 0, 0
            with ThreadPoolExecutor(DOWNLOAD_THREADS) as pool:
                for downloaded in pool.map(lambda url: self._get(http, url, urls)[1], tiles):
                    new, done = new + downloaded, done + 1
                    if done % 50 == 0 or done == len(tiles):
                        say(f"{name}: {done} / {len(tiles)} tiles ({new} downloaded, {done - new} from the mirror)")
        log.info("%s: %d tiles within %.0f m, %d downloaded, %d from %s", name, len(tiles), radius_m, new,
                 len(tiles) - new, self.download_dir)
        say(f"{name}: loading {len(tiles)} tiles")

        def resolve(ts_path: Path, uri: str) -> Path | None:  # outside the radius: not fetched, left out
            path = self._local_path(urljoin(urls[ts_path], uri))
            return path if path in urls else None

        try:
            return [load_3dtiles(local, self.sample_spacing_m, resolve=resolve)]
        except GisFormatError as e:
            if "no b3dm/pnts/glb content" in str(e):
                return []
            raise

    def _local_path(self, url: str) -> Path:
        """Where url is mirrored: download_dir/host/path. A path that would leave the folder once
        decoded (``%2e%2e/`` from a hostile or broken server) is refused, not written."""
        parts = urlsplit(url)
        root = self.download_dir.resolve()
        dst = (root / parts.netloc.replace(":", "_") / unquote(parts.path).lstrip("/")).resolve()
        if not dst.is_relative_to(root) or dst == root:
            raise FetchError(_redacted(f"{url}: the path leaves the download folder; refused"))
        return dst

    def _get(self, http: requests.Session, url: str, urls: dict[Path, str], refresh: bool = False) -> tuple[Path, bool]:
        """(the mirrored file, whether it was downloaded now)."""
        dst = self._local_path(url)
        urls[dst] = url
        if dst.is_file() and not refresh:
            return dst, False
        try:
            r = http.get(url, timeout=self.timeout_s)
            r.raise_for_status()
        except requests.RequestException as e:
            if dst.is_file():
                log.warning("%s: %s; using the copy downloaded before", _redacted(url), type(e).__name__)
                return dst, False
            raise FetchError(_redacted(f"{url}: {type(e).__name__}: {e}")) from None
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_name(f"{dst.name}.{threading.get_ident()}.part")
        tmp.write_bytes(r.content)
        tmp.replace(dst)
        return dst, True

    def _download(self, http: requests.Session, url: str, T_parent: np.ndarray, refine: str, centre: np.ndarray,
                  radius_m: float, depth: int, urls: dict[Path, str], tiles: list[str]) -> Path:
        if depth > 16:
            raise FetchError(_redacted(f"{url}: external tilesets nested deeper than 16"))
        path, _ = self._get(http, url, urls, refresh=depth == 0)
        try:
            doc = json.loads(path.read_text())
            contents = list(tileset_contents(  # (implicit tiling: its subtrees are mirrored as the walk reaches them)
                doc["root"], T_parent, refine, self.sample_spacing_m,
                keep=lambda tile, T: _near(tile.get("boundingVolume", {}), T, centre, radius_m),
                read_subtree=lambda uri: self._get(http, _child_url(url, uri), urls)[0].read_bytes()))
        except ImplicitTilingError as e:
            raise FetchError(_redacted(f"{url}: {e}")) from None
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, UnicodeDecodeError) as e:
            path.unlink(missing_ok=True)
            raise FetchError(_redacted(f"{url}: not a 3D Tiles tileset ({type(e).__name__}: {e})")) from None
        for c in contents:
            if c.is_tileset:
                self._download(http, _child_url(url, c.uri), c.T, c.refine, centre, radius_m, depth + 1, urls, tiles)
            else:
                tiles.append(_child_url(url, c.uri))
        return path


def _redacted(text: str) -> str:
    """text with the values of credential-like URL parameters (key, token, access_token) blanked:
    errors and logs go to the journal, an API key does not."""
    return re.sub(r"(?i)\b(key|token|access_token)=[^&\s]+", r"\1=…", text)


def _child_url(base: str, uri: str) -> str:
    """The URL of ``uri`` named in the document at ``base``: resolved against it (RFC 3986), with
    the URI's own query parameters first and then those of ``base`` it does not set (an API key, a
    session), so that every request down the tree carries them."""
    parts = urlsplit(urljoin(base, uri))
    own = parse_qsl(parts.query, keep_blank_values=True)
    names = {k for k, _ in own}
    merged = own + [(k, v) for k, v in parse_qsl(urlsplit(base).query, keep_blank_values=True) if k not in names]
    return urlunsplit(parts._replace(query=urlencode(merged)))


def _near(bv: dict, T: np.ndarray, centre: np.ndarray, radius_m: float) -> bool:
    """Does a 3D Tiles bounding volume come within radius_m of centre (ECEF)? Unknown → yes."""
    if "sphere" in bv:
        c = T[:3, :3] @ np.asarray(bv["sphere"][:3]) + T[:3, 3]
        return float(np.linalg.norm(c - centre)) <= radius_m + bv["sphere"][3]
    if "box" in bv:
        b = np.asarray(bv["box"], float)
        c = T[:3, :3] @ b[:3] + T[:3, 3]
        half = float(np.sum(np.linalg.norm(b[3:].reshape(3, 3), axis=1)))
        return float(np.linalg.norm(c - centre)) <= radius_m + half
    if "region" in bv:  # [west, south, east, north] rad, [min h, max h] m
        w, s, e, n, _, _ = bv["region"]
        lat, lon = np.degrees((s + n) / 2), np.degrees((w + e) / 2)
        f = LocalFrame(float(lat), float(lon))
        corner = f.geodetic_to_enu(np.degrees(n), np.degrees(e), 0.0)
        c = f.ecef_to_enu(centre)
        return float(np.linalg.norm(c[:2])) <= radius_m + float(np.linalg.norm(corner[:2]))
    return True


def fetch_model(providers: list, lat_deg: float, lon_deg: float, radius_m: float, source: str = "fetch") -> GisModel:
    """All models the providers find within radius_m of (lat, lon), merged; FetchError if none."""
    models = [m for p in providers for m in p.fetch(lat_deg, lon_deg, radius_m)]
    if not models:
        raise FetchError(f"no GIS model within {radius_m:.0f} m of {lat_deg:.6f}, {lon_deg:.6f}")
    return models[0] if len(models) == 1 else merge_models(models, source)


def providers_for(sources: Sequence[str], cfg: GisConfig, download_dir: Path,
                  progress: Callable[[str], None] | None = None) -> list:
    """A provider per source: an http(s):// URL is a 3D Tiles server (mirrored into download_dir),
    anything else a model file or a directory of them; sampled as ``cfg`` says."""
    return [HttpTilesProvider(s, download_dir, cfg.fetch_timeout_s, cfg.sample_spacing_m, progress=progress)
            if s.startswith(("http://", "https://")) else LocalProvider((Path(s).expanduser(),), cfg.sample_spacing_m, cfg.footprint_ground)
            for s in sources]


class NoSiteError(LookupError):
    """No cached site covers a position and nothing could be fetched for it."""


def site_at(cache: GisCache, lat_deg: float, lon_deg: float, cfg: GisConfig,
            progress: Callable[[str], None] | None = None) -> tuple[str, str]:
    """The GIS site for a rough position (TerraSLAM §6): Pre-fetch (the nearest cached site whose
    coverage contains it), else Fetch from ``cfg.fetch_sources`` within ``cfg.fetch_radius_m`` and
    SaveCache as a new site. Returns (site id, how it was found). NoSiteError when no cached site
    covers the position and there is nothing to fetch from; FetchError / GisFormatError when the
    fetch fails."""
    hit = cache.prefetch(lat_deg, lon_deg)
    if hit is not None:
        return hit.site_id, "cached"
    where = f"{lat_deg:.6f}, {lon_deg:.6f}"
    if not cfg.fetch_sources:
        known = ", ".join(e.site_id for e in cache.entries()) or "none"
        raise NoSiteError(f"no site of the GIS cache {cache.root} covers {where} (sites: {known}) and gis.fetch_sources "
                          "is empty: `terraslam gis import` / `gis fetch` one, or set gis.fetch_sources")
    model = fetch_model(providers_for(cfg.fetch_sources, cfg, cache.root / "downloads", progress),
                        lat_deg, lon_deg, cfg.fetch_radius_m, ",".join(cfg.fetch_sources))
    site_id = cache.save_model(model)
    if cache.prefetch(lat_deg, lon_deg) is None:  # within the radius, yet not under the position
        log.warning("site %s fetched for %s does not cover it: fixes only where it has structure", site_id, where)
    return site_id, "fetched"
