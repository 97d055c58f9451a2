"""GIS cache (TerraSLAM §6: Pre-fetch, SaveCache): models + per-site transforms in SQLite.

Layout under ``root``: ``index.sqlite`` (tables ``models``, ``transforms``, ``georef``: the
evidence on a model's georeference gathered against GNSS over the flights so far, ``imports``:
which site a model file was imported as, so an unchanged file is mapped, not parsed again, and
``survey_maps``: a site's survey SLAM map), ``models/<sha256>.npz`` (the GisModel arrays, stored
cell by cell and memory-mapped on load) and ``maps/<sha256>.npz`` (survey SLAM maps, slam/persist.py
files holding their T_rough: the service starts in one without GNSS). Every file and row carries a
SHA-256 content hash that is checked on load; a mismatch raises CacheCorrupt naming the entry.
A site covers the disc of ``radius_m`` around its model's ENU origin; ``prefetch`` returns the
nearest site covering a position, with its T_rough, latest T_fine and georeference evidence.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gis.align.georef import GeorefEvidence
from gis.config import AUTO_SITE
from gis.geodesy import LocalFrame
from gis.model import GisFormatError, GisModel, model_from_npz
from gis.sim3 import Sim3

KINDS = ("rough", "fine")
_SCHEMA = """
CREATE TABLE IF NOT EXISTS models (
    site_id TEXT PRIMARY KEY, lat0_deg REAL, lon0_deg REAL, h0_ellipsoid_m REAL, radius_m REAL,
    file TEXT, sha256 TEXT, source_crs TEXT, source_path TEXT, n_points INTEGER, saved_unix_s REAL);
CREATE TABLE IF NOT EXISTS transforms (
    site_id TEXT, kind TEXT, matrix_json TEXT, meta_json TEXT, sha256 TEXT, saved_unix_s REAL,
    PRIMARY KEY (site_id, kind));
CREATE TABLE IF NOT EXISTS georef (
    site_id TEXT PRIMARY KEY, evidence_json TEXT, sha256 TEXT, saved_unix_s REAL);
CREATE TABLE IF NOT EXISTS imports (source_key TEXT PRIMARY KEY, site_id TEXT, saved_unix_s REAL);
CREATE TABLE IF NOT EXISTS survey_maps (site_id TEXT PRIMARY KEY, file TEXT, sha256 TEXT, saved_unix_s REAL);
"""


class CacheCorrupt(RuntimeError):
    """A cached file or row does not match its stored content hash (or is missing)."""


@dataclass(frozen=True)
class CacheEntry:
    site_id: str
    origin: LocalFrame
    radius_m: float
    model_file: Path
    sha256: str
    source_crs: str
    source_path: str
    n_points: int
    T_rough: Sim3 | None = None
    T_fine: Sim3 | None = None
    meta: dict = field(default_factory=dict)
    georef: GeorefEvidence | None = None  # the model's georeference measured against GNSS (gis.align.georef)


class GisCache:
    def __init__(self, root: Path | str) -> None:
        self.root = Path(root).expanduser()
        (self.root / "models").mkdir(parents=True, exist_ok=True)
        self.db_path = self.root / "index.sqlite"
        with self._db() as db:
            db.executescript(_SCHEMA)

    def _db(self) -> sqlite3.Connection:
        return sqlite3.connect(self.db_path, timeout=10.0)

    # --- SaveCache ---------------------------------------------------------------------------
    def save_model(self, model: GisModel, site_id: str | None = None, source_key: str | None = None) -> str:
        """Store a model (content-addressed .npz, uncompressed, its points stored cell by cell of
        the crop index so that ``load_model`` can map it instead of reading it) and index it;
        returns its site id."""
        if site_id == AUTO_SITE:
            raise ValueError(f"{AUTO_SITE!r} is not a site id: gis.site: {AUTO_SITE} means the site covering the position")
        model = model.sorted_by_cell
        tmp = self.root / "models" / f".tmp-{time.time_ns()}.npz"
        np.savez(
            tmp, points_enu=model.points_enu, normals_enu=model.normals_enu, labels=model.labels,
            origin=np.array([model.origin.lat0_deg, model.origin.lon0_deg, model.origin.h0_ellipsoid_m]),
        )
        digest = _sha256_file(tmp)
        final = self.root / "models" / f"{digest}.npz"
        tmp.replace(final)
        site_id = site_id or f"{model.source_path.stem}-{digest[:8]}"
        radius = float(np.max(np.linalg.norm(model.points_enu[:, :2], axis=1)))
        with self._db() as db:
            db.execute(
                "INSERT OR REPLACE INTO models VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                (site_id, model.origin.lat0_deg, model.origin.lon0_deg, model.origin.h0_ellipsoid_m, radius,
                 final.name, digest, model.source_crs, str(model.source_path), len(model), time.time()),
            )
            if source_key is not None:
                db.execute("INSERT OR REPLACE INTO imports VALUES (?,?,?)", (source_key, site_id, time.time()))
        return site_id

    def save_survey_map(self, site_id: str, map_file: Path | str) -> Path:
        """Store (a copy of) a survey SLAM map file for a site, replacing the previous one; returns
        the cached file. The file is a slam/persist.py map whose header carries its T_rough
        (``companion.persistence.SURVEY_ALIGNMENT``); its own content hash is checked when the
        service loads it, this row's hash when the cache hands it out."""
        self._site(site_id)
        (self.root / "maps").mkdir(exist_ok=True)
        tmp = self.root / "maps" / f".tmp-{time.time_ns()}.npz"
        shutil.copyfile(map_file, tmp)
        digest = _sha256_file(tmp)
        final = self.root / "maps" / f"{digest}.npz"
        tmp.replace(final)
        with self._db() as db:
            old = db.execute("SELECT file FROM survey_maps WHERE site_id=?", (site_id,)).fetchone()
            db.execute("INSERT OR REPLACE INTO survey_maps VALUES (?,?,?,?)", (site_id, final.name, digest, time.time()))
        if old is not None and old[0] != final.name:
            self._drop_map_file(old[0])
        return final

    def survey_map(self, site_id: str) -> Path | None:
        """The site's survey SLAM map file, or None; CacheCorrupt when it is missing or does not
        match its SHA-256."""
        with self._db() as db:
            r = db.execute("SELECT file, sha256 FROM survey_maps WHERE site_id=?", (site_id,)).fetchone()
        if r is None:
            return None
        path = self.root / "maps" / r[0]
        if not path.is_file():
            raise CacheCorrupt(f"site {site_id!r}: survey map {path} is missing")
        if _sha256_file(path) != r[1]:
            raise CacheCorrupt(f"site {site_id!r}: survey map {path} does not match its SHA-256 (corrupted)")
        return path

    def _drop_map_file(self, name: str) -> int:
        """Delete a survey map file no site refers to any more; the bytes freed."""
        with self._db() as db:
            if db.execute("SELECT COUNT(*) FROM survey_maps WHERE file=?", (name,)).fetchone()[0]:
                return 0
        path = self.root / "maps" / name
        if not path.is_file():
            return 0
        size = path.stat().st_size
        path.unlink()
        return size

    def imported(self, source_key: str) -> str | None:
        """The site whose model was saved from the source ``source_key`` names
        (``gis.loaders.source_key``: the same file, unchanged, the same settings), or None."""
        with self._db() as db:
            r = db.execute("SELECT site_id FROM imports WHERE source_key=?", (source_key,)).fetchone()
        return r[0] if r is not None and self._row(r[0]) is not None else None

    def save_transform(self, site_id: str, kind: str, T_ecef_slam: Sim3, meta: dict | None = None) -> None:
        """Store T_rough or (replacing the previous) the latest T_fine of a site."""
        if kind not in KINDS:
            raise ValueError(f"transform kind must be one of {KINDS}, got {kind!r}")
        self._site(site_id)
        mj = json.dumps(T_ecef_slam.matrix().tolist())
        meta_j = json.dumps(meta or {}, sort_keys=True, default=str)
        with self._db() as db:
            db.execute("INSERT OR REPLACE INTO transforms VALUES (?,?,?,?,?,?)",
                       (site_id, kind, mj, meta_j, _sha256_text(mj + meta_j), time.time()))

    def save_georef(self, site_id: str, evidence: GeorefEvidence) -> None:
        """Store (replacing the previous) the evidence on the site model's georeference, all flights
        so far (gis.align.georef): the next flight at the site starts from it."""
        self._site(site_id)
        j = json.dumps({"info": evidence.info.tolist(), "info_d": evidence.info_d.tolist(),
                        "dWd": evidence.dWd, "n": evidence.n}, sort_keys=True)
        with self._db() as db:
            db.execute("INSERT OR REPLACE INTO georef VALUES (?,?,?,?)", (site_id, j, _sha256_text(j), time.time()))

    def load_georef(self, site_id: str) -> GeorefEvidence | None:
        """The stored georeference evidence of a site, or None; CacheCorrupt when the row does not
        match its hash or does not hold valid evidence."""
        with self._db() as db:
            r = db.execute("SELECT evidence_json, sha256 FROM georef WHERE site_id=?", (site_id,)).fetchone()
        if r is None:
            return None
        if _sha256_text(r[0]) != r[1]:
            raise CacheCorrupt(f"site {site_id!r}: stored georeference evidence does not match its SHA-256 (corrupted)")
        try:
            d = json.loads(r[0])
            return GeorefEvidence(np.asarray(d["info"], float), np.asarray(d["info_d"], float), float(d["dWd"]), int(d["n"]))
        except (ValueError, KeyError, TypeError) as e:
            raise CacheCorrupt(f"site {site_id!r}: stored georeference evidence is invalid: {e}") from e

    # --- load / Pre-fetch --------------------------------------------------------------------
    def load_model(self, site_id: str) -> GisModel:
        row = self._site(site_id)
        path = self._file(row)
        if not path.is_file():
            raise CacheCorrupt(f"site {site_id!r}: model file {path} is missing")
        if _sha256_file(path) != row["sha256"]:
            raise CacheCorrupt(f"site {site_id!r}: model file {path} does not match its SHA-256 (corrupted)")
        try:
            return model_from_npz(path, row["source_crs"], Path(row["source_path"]))
        except GisFormatError as e:
            raise CacheCorrupt(f"site {site_id!r}: {e}") from None

    def load_transform(self, site_id: str, kind: str) -> tuple[Sim3, dict] | None:
        with self._db() as db:
            r = db.execute("SELECT matrix_json, meta_json, sha256 FROM transforms WHERE site_id=? AND kind=?",
                           (site_id, kind)).fetchone()
        if r is None:
            return None
        if _sha256_text(r[0] + r[1]) != r[2]:
            raise CacheCorrupt(f"site {site_id!r}: stored T_{kind} does not match its SHA-256 (corrupted)")
        return Sim3.from_matrix(np.asarray(json.loads(r[0]))), json.loads(r[1])

    def entries(self) -> list[CacheEntry]:
        with self._db() as db:
            db.row_factory = sqlite3.Row
            rows = db.execute("SELECT * FROM models ORDER BY site_id").fetchall()
        return [self._entry(r) for r in rows]

    def prefetch(self, lat_deg: float, lon_deg: float) -> CacheEntry | None:
        """The nearest cached site whose coverage contains (lat, lon), with its transforms; else None."""
        best = None
        for e in self.entries():
            d = float(np.linalg.norm(e.origin.geodetic_to_enu(lat_deg, lon_deg, e.origin.h0_ellipsoid_m)[:2]))
            if d <= e.radius_m and (best is None or d < best[0]):
                best = (d, e)
        return None if best is None else best[1]

    def remove(self, site_id: str) -> int:
        """Forget a site: its model row, transforms, georeference evidence, imports and survey map;
        its model file is deleted unless another site holds the same content. Returns the bytes freed.
        KeyError if there is no such site. (A running service that mapped the file keeps its
        pages: the file's inode lives until it unmaps it.)"""
        row = self._site(site_id)
        with self._db() as db:
            survey = db.execute("SELECT file FROM survey_maps WHERE site_id=?", (site_id,)).fetchone()
            for table in ("models", "transforms", "georef", "imports", "survey_maps"):
                db.execute(f"DELETE FROM {table} WHERE site_id=?", (site_id,))  # noqa: S608 (fixed table names)
            shared = db.execute("SELECT COUNT(*) FROM models WHERE file=?", (row["file"],)).fetchone()[0]
        freed = 0 if survey is None else self._drop_map_file(survey[0])
        path = self._file(row)
        if shared or not path.is_file():
            return freed
        size = path.stat().st_size
        path.unlink()
        return freed + size

    def model_file(self, site_id: str) -> Path:
        """The cached model file of a site (an .npz ``gis.loaders.load_model`` reads too)."""
        return self._file(self._site(site_id))

    def _site(self, site_id: str) -> sqlite3.Row:
        """The model row of a site; KeyError when there is none."""
        row = self._row(site_id)
        if row is None:
            raise KeyError(f"no cached model for site {site_id!r}")
        return row

    def _file(self, row: sqlite3.Row) -> Path:
        return self.root / "models" / row["file"]

    def _row(self, site_id: str):
        with self._db() as db:
            db.row_factory = sqlite3.Row
            return db.execute("SELECT * FROM models WHERE site_id=?", (site_id,)).fetchone()

    def _entry(self, r) -> CacheEntry:
        rough = self.load_transform(r["site_id"], "rough")
        fine = self.load_transform(r["site_id"], "fine")
        meta = {k: t[1] for k, t in (("rough", rough), ("fine", fine)) if t}
        try:
            origin, radius_m = LocalFrame(r["lat0_deg"], r["lon0_deg"], r["h0_ellipsoid_m"]), float(r["radius_m"])
        except (TypeError, ValueError) as e:
            raise CacheCorrupt(f"site {r['site_id']!r}: its index row does not hold an origin and radius ({e})") from None
        return CacheEntry(
            r["site_id"], origin, radius_m,
            self._file(r), r["sha256"], r["source_crs"], r["source_path"], r["n_points"],
            rough[0] if rough else None, fine[0] if fine else None, meta, self.load_georef(r["site_id"]),
        )


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _sha256_text(s: str) -> str:
    return hashlib.sha256(s.encode("utf-8")).hexdigest()
