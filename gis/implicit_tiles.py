"""3D Tiles 1.1 implicit tiling, expanded into explicit tiles one level at a time.

A tile with ``implicitTiling`` (a quadtree or octree, as 3D Tiles 1.1 tilers may write for large
terrain or point-cloud tilesets) lists no children: they follow from its bounding volume, halved per level,
its geometric error, halved per level, and availability bitstreams in subtree files (3D Tiles 1.1
§"Implicit Tiling", §"Subtrees"). ``implicit_root`` turns such a tile into a plain tile dict
whose children ``implicit_children`` makes on demand, so ``gis.loaders.tileset_contents`` walks it
like any tileset and reads only the subtrees the walk reaches (a terrain tileset's tree is huge;
its selection for one site is not).

Hand-written: no library among our dependencies reads subtree files for a selection walk, and
the format is small: a 24-byte header, JSON, one binary chunk.
"""
from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

IMPLICIT = "_implicit"  # key of the expansion state in a tile dict made here (not a 3D Tiles property)
MAX_TILES = 200_000  # tiles one expansion may make: a few bytes of constant availability can describe 4^20
SUBTREE_MAGIC = b"subt"


class ImplicitTilingError(ValueError):
    """A subtree or an implicit tile that cannot be read (names what is wrong)."""


@dataclass
class Subtree:
    """Availability of one subtree: bit i of each stream is the tile / content / child subtree with
    index i (levels one after the other, Morton order within a level)."""
    tiles: Callable[[int], bool]
    contents: list[Callable[[int], bool]]
    child_subtrees: Callable[[int], bool]


NOTHING = Subtree(lambda i: False, [], lambda i: False)  # a subtree the reader leaves out (e.g. not fetched)


@dataclass
class _Tiling:
    """What every tile of one implicit tree shares."""
    root: dict  # the tile with implicitTiling (its boundingVolume, geometricError, content templates)
    octree: bool
    subtree_levels: int
    available_levels: int
    subtree_uri: str
    read: Callable[[str], bytes | None]  # subtree URI (relative to the tileset) → its bytes; None: left out
    subtrees: dict[tuple[int, int, int, int], Subtree] = field(default_factory=dict)
    n_tiles: int = 0  # tiles made so far (MAX_TILES)

    def subtree(self, level: int, x: int, y: int, z: int) -> Subtree:
        key = (level, x, y, z)
        if key not in self.subtrees:
            uri = fill_template(self.subtree_uri, level, x, y, z)
            data = self.read(uri)
            self.subtrees[key] = (NOTHING if data is None else
                                  parse_subtree(data, self.octree, self.subtree_levels, uri, self.read))
        return self.subtrees[key]


def fill_template(template: str, level: int, x: int, y: int, z: int) -> str:
    """A template URI with its {level}, {x}, {y}, {z} filled in."""
    return template.replace("{level}", str(level)).replace("{x}", str(x)).replace("{y}", str(y)).replace("{z}", str(z))


def morton(x: int, y: int, z: int, octree: bool) -> int:
    """The Morton (Z-order) index of a tile within its level: bits of x, y (and z) interleaved, x lowest."""
    n, i, bit = (3 if octree else 2), 0, 0
    while (x | y | z) >> bit:
        i |= ((x >> bit) & 1) << (n * bit)
        i |= ((y >> bit) & 1) << (n * bit + 1)
        if octree:
            i |= ((z >> bit) & 1) << (n * bit + 2)
        bit += 1
    return i


def implicit_root(tile: dict, read: Callable[[str], bytes | None] | None) -> dict:
    """``tile`` (with ``implicitTiling``) as the root of its expansion: the same tile, with the
    content of tile (0, 0, 0, 0) if available, its children made on demand by implicit_children.
    ``read``: a subtree's bytes by URI, or None to leave that subtree (and the tiles below it) out."""
    if read is None:
        raise ImplicitTilingError("implicit tiling needs its subtree files, and this reader was given none")
    it = tile["implicitTiling"]
    scheme = str(it["subdivisionScheme"]).upper()
    if scheme not in ("QUADTREE", "OCTREE"):
        raise ImplicitTilingError(f"implicitTiling.subdivisionScheme {scheme!r} is neither QUADTREE nor OCTREE")
    bv = tile["boundingVolume"]
    if "box" not in bv and "region" not in bv:
        raise ImplicitTilingError(f"implicit tiling over a {sorted(bv)} bounding volume: only box and region are read")
    tiling = _Tiling(tile, scheme == "OCTREE", int(it["subtreeLevels"]), int(it["availableLevels"]),
                     str(it["subtrees"]["uri"]), read)
    if tiling.subtree_levels < 1 or tiling.available_levels < 1:
        raise ImplicitTilingError("implicitTiling.subtreeLevels and availableLevels must be >= 1")
    root = {k: v for k, v in tile.items() if k not in ("implicitTiling", "content", "contents", "children")}
    root.update(_tile_at(tiling, 0, 0, 0, 0))  # (its transform and refine stay; level 0's volume is its own)
    return root


def implicit_children(tile: dict, wanted: Callable[[dict], bool] = lambda child: True) -> list[dict]:
    """The available children of a tile made by implicit_root / implicit_children; those ``wanted``
    refuses by their volume (e.g. outside a fetch radius) are left out before their availability
    is read, so their subtrees are never read."""
    tiling, level, x, y, z = tile[IMPLICIT]
    if level + 1 >= tiling.available_levels:
        return []
    kids = []
    for dz in ((0, 1) if tiling.octree else (0,)):
        for dy in (0, 1):
            for dx in (0, 1):
                c = (level + 1, 2 * x + dx, 2 * y + dy, 2 * z + dz)
                if wanted({"boundingVolume": _sub_volume(tiling.root["boundingVolume"], *c, tiling.octree)}) \
                        and _available(tiling, *c):
                    kids.append(_tile_at(tiling, *c))
    return kids


def _subtree_of(tiling: _Tiling, level: int, x: int, y: int, z: int) -> tuple[Subtree, int, int] | None:
    """The subtree holding tile (level, x, y, z), the tile's level within it and its index there;
    None when that subtree is not available (its parent subtree says so)."""
    n = tiling.subtree_levels
    root_level = (level // n) * n
    shift = level - root_level
    sx, sy, sz = x >> shift, y >> shift, z >> shift
    if root_level > 0:  # is this subtree available? its parent subtree's child-subtree bit says
        parent = _subtree_of(tiling, root_level - n, sx >> n, sy >> n, sz >> n)
        mask = (1 << n) - 1
        if parent is None or not parent[0].child_subtrees(morton(sx & mask, sy & mask, sz & mask, tiling.octree)):
            return None
    sub = tiling.subtree(root_level, sx, sy, sz)
    mask = (1 << shift) - 1
    branch = 8 if tiling.octree else 4
    offset = (branch ** shift - 1) // (branch - 1)
    return sub, shift, offset + morton(x & mask, y & mask, z & mask, tiling.octree)


def _available(tiling: _Tiling, level: int, x: int, y: int, z: int) -> bool:
    found = _subtree_of(tiling, level, x, y, z)
    return found is not None and found[0].tiles(found[2])


def _tile_at(tiling: _Tiling, level: int, x: int, y: int, z: int) -> dict:
    """The explicit tile (level, x, y, z): its volume and geometric error, its content if available."""
    tiling.n_tiles += 1
    if tiling.n_tiles > MAX_TILES:
        raise ImplicitTilingError(f"the selection needs more than {MAX_TILES} tiles of its implicit tiling (level {level}): "
                                  "a sampling spacing far finer than the tileset's use, or a broken tileset")
    root = tiling.root
    t = {"boundingVolume": _sub_volume(root["boundingVolume"], level, x, y, z, tiling.octree),
         "geometricError": float(root["geometricError"]) / 2 ** level, IMPLICIT: (tiling, level, x, y, z)}
    found = _subtree_of(tiling, level, x, y, z)
    templates = ([root["content"]] if "content" in root else []) + list(root.get("contents") or [])
    contents = [{**c, "uri": fill_template(c["uri"], level, x, y, z)}
                for k, c in enumerate(templates)
                if found is not None and k < len(found[0].contents) and found[0].contents[k](found[2])]
    if contents:
        t["contents"] = contents
    return t


def _sub_volume(bv: dict, level: int, x: int, y: int, z: int, octree: bool) -> dict:
    """The bounding volume of tile (level, x, y, z): the root's, split 2^level ways along x and y
    (and z for an octree): a box along its half-axes, a region in longitude, latitude (and height)."""
    n = 2 ** level
    if "box" in bv:
        b = np.asarray(bv["box"], float)
        c, half = b[:3], b[3:].reshape(3, 3)
        f = [(2 * x + 1) / n - 1, (2 * y + 1) / n - 1, ((2 * z + 1) / n - 1) if octree else 0.0]
        s = [1 / n, 1 / n, (1 / n) if octree else 1.0]
        return {"box": (c + f @ half).tolist() + (half * np.array(s)[:, None]).reshape(-1).tolist()}
    w, so, e, no, h0, h1 = (float(v) for v in bv["region"])
    dlon, dlat, dh = (e - w) / n, (no - so) / n, ((h1 - h0) / n if octree else h1 - h0)
    hz = h0 + (z * dh if octree else 0.0)
    return {"region": [w + x * dlon, so + y * dlat, w + (x + 1) * dlon, so + (y + 1) * dlat, hz, hz + dh]}


def parse_subtree(data: bytes, octree: bool, subtree_levels: int, uri: str,
                  read: Callable[[str], bytes | None]) -> Subtree:
    """A subtree file: binary (``subt`` magic, version 1, JSON and binary lengths as uint64, the
    JSON, the binary chunk) or JSON, with its buffers internal or external (read by URI, relative
    to the subtree). Availability is a constant or a bitstream (bit i in byte i // 8, bit i % 8)."""
    if data[:4] == SUBTREE_MAGIC:
        if len(data) < 24:
            raise ImplicitTilingError(f"subtree {uri}: truncated header")
        _, version, n_json, n_bin = struct.unpack("<4sIQQ", data[:24])
        if version != 1:
            raise ImplicitTilingError(f"subtree {uri}: version {version}, this reads 1")
        if 24 + n_json + n_bin > len(data):
            raise ImplicitTilingError(f"subtree {uri}: truncated ({len(data)} bytes, the header says {24 + n_json + n_bin})")
        doc_bytes, internal = data[24:24 + n_json], data[24 + n_json:24 + n_json + n_bin]
    else:
        doc_bytes, internal = data, b""
    try:
        doc = json.loads(doc_bytes)
        buffers = []
        for b in doc.get("buffers", []):
            raw = read(_beside(uri, b["uri"])) if "uri" in b else internal
            if raw is None:
                raise ImplicitTilingError(f"subtree {uri}: its buffer {b['uri']} is not available")
            if len(raw) < int(b["byteLength"]):
                raise ImplicitTilingError(f"subtree {uri}: buffer of {len(raw)} bytes, byteLength {b['byteLength']}")
            buffers.append(raw)
        views = doc.get("bufferViews", [])
        branch = 8 if octree else 4
        n_tiles = (branch ** subtree_levels - 1) // (branch - 1)
        n_children = branch ** subtree_levels

        def stream(a: dict, n_bits: int) -> Callable[[int], bool]:
            if "constant" in a:
                on = bool(int(a["constant"]))
                return lambda i: on
            v = views[int(a["bitstream"] if "bitstream" in a else a["bufferView"])]
            off, length = int(v.get("byteOffset", 0)), int(v["byteLength"])
            bits = np.frombuffer(buffers[int(v["buffer"])][off:off + length], np.uint8)
            if len(bits) * 8 < n_bits:
                raise ImplicitTilingError(f"subtree {uri}: a bitstream of {len(bits)} bytes for {n_bits} bits")
            return lambda i: bool((bits[i >> 3] >> (i & 7)) & 1)

        content = doc.get("contentAvailability", [])
        if isinstance(content, dict):  # (the 3DTILES_implicit_tiling extension's single object)
            content = [content]
        return Subtree(stream(doc["tileAvailability"], n_tiles), [stream(c, n_tiles) for c in content],
                       stream(doc["childSubtreeAvailability"], n_children))
    except ImplicitTilingError:
        raise
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, IndexError, TypeError, ValueError) as e:
        raise ImplicitTilingError(f"subtree {uri}: {type(e).__name__}: {e}") from None


def _beside(uri: str, name: str) -> str:
    """``name`` relative to the folder of ``uri`` (both tileset-relative)."""
    head = uri.rsplit("/", 1)[0] + "/" if "/" in uri else ""
    return head + name
