#!/usr/bin/python3
"""The OGC 3D Tiles view of a real merged model, end to end: the real vsmd on 127.0.0.1:0 (see
harness.py) over a data root holding PRISM with Jacksboro merged into it
(imported at 65 x 65 by `vsm import`, merged by `vsm merge`: the `tiles.prepare` fixture), then

- tileset.json fetched and checked against the 3D Tiles 1.1 rules with our own reader: asset
  version, geometricError strictly decreasing from parent to child (0 at leaves), children's
  bounding volumes inside their parent's, every content URI resolving (200, model/gltf-binary)
  and naming its patch's version ("{key}.glb?v={version}", the version of the hierarchy route);
- every GLB decoded independently (struct, json): header and chunks, accessor min/max equal to the
  data, positions (through the tile transforms and glTF's y-up -> z-up rotation) inside the tile's
  bounding volume, and one triangle pair per complete quad of the patch's own grid (fetched as
  .aara from /positions);
- every GLB validated by Khronos' glTF validator (npm `gltf-validator`, installed into the build
  directory by install-node-tools.sh): zero errors;
- ETags (If-None-Match -> 304), CORS, HEAD, and errors for unknown tiles;
- a repeated GLB request answered from the GLB cache (a hit in /v1/stats, the same bytes).

Run by ctest:
    tiles_test.py --vsmd build/server/vsmd --model build/.../tiles/merged \\
        --node-tools build/node-tools --validator tests/integration/validate_gltf.js"""

import argparse
import gzip
import json
import math
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from harness import Daemon, decode_aara  # noqa: E402

ARGS = None
MODEL = "merged"
PREFIX = "/v1/models/%s/3dtiles/" % MODEL
# The tileset of uncompressed (float32) content, which this test's own reader decodes; the default
# one names the KHR_mesh_quantization + EXT_meshopt_compression GLBs.
RAW_TILESET = "tileset.json?compress=none"


# ---- an independent reader of GLB and 3D Tiles -------------------------------------------------

COMPONENT = {5126: ("f", 4), 5125: ("I", 4), 5123: ("H", 2), 5121: ("B", 1)}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def decode_glb(data):
    """(gltf JSON, BIN bytes) of a GLB, checking the container per the glTF 2.0 spec."""
    assert len(data) >= 20, "GLB shorter than header + chunk header"
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF", magic
    assert version == 2, version
    assert length == len(data), (length, len(data))
    assert length % 4 == 0
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON", json_type
    assert json_length % 4 == 0
    gltf = json.loads(data[20:20 + json_length].decode("utf-8"))
    at = 20 + json_length
    bin_chunk = b""
    if at < length:
        bin_length, bin_type = struct.unpack_from("<I4s", data, at)
        assert bin_type == b"BIN\0", bin_type
        assert bin_length % 4 == 0
        assert at + 8 + bin_length == length
        bin_chunk = data[at + 8:at + 8 + bin_length]
        assert gltf["buffers"][0]["byteLength"] <= len(bin_chunk)
    return gltf, bin_chunk


def read_accessor(gltf, bin_chunk, index):
    """The accessor's elements as a flat list (tightly packed views only, as vsm writes)."""
    accessor = gltf["accessors"][index]
    view = gltf["bufferViews"][accessor["bufferView"]]
    fmt, size = COMPONENT[accessor["componentType"]]
    width = WIDTH[accessor["type"]]
    offset = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    assert offset % size == 0, "misaligned accessor %d" % index
    assert "byteStride" not in view or view["byteStride"] == size * width
    count = accessor["count"] * width
    assert count * size <= view["byteLength"]
    return list(struct.unpack_from("<%d%s" % (count, fmt), bin_chunk, offset))


def matmul(a, b):
    """Product of two column-major 4x4 matrices (3D Tiles' layout)."""
    return [sum(a[k * 4 + r] * b[c * 4 + k] for k in range(4)) for c in range(4) for r in range(4)]


def apply(m, p):
    """A column-major 4x4 matrix applied to a point."""
    return [m[r] * p[0] + m[4 + r] * p[1] + m[8 + r] * p[2] + m[12 + r] for r in range(3)]


IDENTITY = [1.0 if r == c else 0.0 for c in range(4) for r in range(4)]


def box_corners(box, m):
    """The eight corners of a 3D Tiles box (centre + three half-axis vectors) under `m`."""
    c, u, v, w = box[0:3], box[3:6], box[6:9], box[9:12]
    out = []
    for su in (-1, 1):
        for sv in (-1, 1):
            for sw in (-1, 1):
                p = [c[i] + su * u[i] + sv * v[i] + sw * w[i] for i in range(3)]
                out.append(apply(m, p))
    return out


def aabb(points):
    return ([min(p[i] for p in points) for i in range(3)],
            [max(p[i] for p in points) for i in range(3)])


def inside(inner, outer, tolerance=0.0):
    (lo1, hi1), (lo2, hi2) = inner, outer
    return all(lo2[i] - tolerance <= lo1[i] and hi1[i] <= hi2[i] + tolerance for i in range(3))


def walk(tile, parent=IDENTITY, parent_tile=None):
    """(tile, world transform, parent tile) for every tile, parents first."""
    world = matmul(parent, tile["transform"]) if "transform" in tile else parent
    yield tile, world, parent_tile
    for child in tile.get("children", []):
        yield from walk(child, world, tile)


def is_external(tile):
    """Whether a tile names an external tileset (a subtree's document) instead of a GLB."""
    return tile["content"]["uri"].partition("?")[0].endswith(".json")


def assemble(daemon, uri, documents=None):
    """The tileset at PREFIX + `uri`, each external tile replaced by the root of the document it
    names, read the same way: the subtree's root keeps the external tile's transform followed by
    its own (3D Tiles composes them so). `documents`, when given, collects (uri, tileset)."""
    status, _, body = daemon.request("GET", PREFIX + uri)
    assert status == 200, (uri, status, body[:200])
    tileset = json.loads(body)
    if documents is not None:
        documents.append((uri, json.loads(body)))

    def expand(tile):
        if is_external(tile):
            assert "children" not in tile, tile["content"]["uri"]
            sub = assemble(daemon, tile["content"]["uri"], documents)["root"]
            sub = dict(sub, transform=matmul(tile["transform"], sub["transform"]))
            return expand_children(sub)
        return expand_children(tile)

    def expand_children(tile):
        if "children" in tile:
            tile = dict(tile, children=[expand(child) for child in tile["children"]])
        return tile

    tileset["root"] = expand(tileset["root"])
    return tileset


def key_of(uri):
    """The patch key of a content URI: "2_1_3.glb?v=4" -> "2_1_3"."""
    path = uri.partition("?")[0]
    assert path.endswith(".glb"), uri
    return path[:-4]


def version_of(uri):
    """The version a content URI names: "2_1_3.glb?v=4" -> 4 (None without one)."""
    query = uri.partition("?")[2]
    params = dict(p.partition("=")[::2] for p in query.split("&") if p)
    return int(params["v"]) if "v" in params else None


def complete_quads(aara):
    name, (w, h), payload = decode_aara(aara)
    assert name == "V3f" and w == h, (name, w, h)
    values = struct.unpack("<%df" % (w * h * 3), payload)
    defined = [not any(math.isnan(values[i * 3 + k]) for k in range(3)) for i in range(w * h)]
    return sum(1 for y in range(h - 1) for x in range(w - 1)
               if defined[y * w + x] and defined[y * w + x + 1] and defined[(y + 1) * w + x]
               and defined[(y + 1) * w + x + 1])


class Tiles(unittest.TestCase):
    daemon = None

    @classmethod
    def setUpClass(cls):
        def prepare(root):
            shutil.copytree(ARGS.model, os.path.join(root, MODEL))

        cls.daemon = Daemon("--set", "threads.cpu=2", prepare=prepare)
        cls.glb_dir = tempfile.mkdtemp(prefix="vsm-glb-")
        start = time.monotonic()
        status, headers, body = cls.daemon.request("GET", PREFIX + RAW_TILESET)
        cls.tileset_seconds = time.monotonic() - start
        assert status == 200, body
        cls.tileset_headers = headers
        cls.tileset_bytes = len(body)
        cls.tileset_document = json.loads(body)
        # The whole tree: the default document names the patches five levels down as external
        # tilesets.
        cls.tileset = assemble(cls.daemon, RAW_TILESET)
        cls.tiles = list(walk(cls.tileset["root"]))
        # Every content, fetched once (the URIs relative to the tileset's URL).
        cls.glbs = {}
        cls.glb_headers = {}
        start = time.monotonic()
        for tile, _, _ in cls.tiles:
            uri = tile["content"]["uri"]
            status, headers, body = cls.daemon.request("GET", PREFIX + uri)
            assert status == 200, (uri, status, body[:200])
            cls.glbs[uri] = body
            cls.glb_headers[uri] = headers
        cls.glb_seconds = time.monotonic() - start
        # The default tileset and its compressed content.
        status, headers, body = cls.daemon.request("GET", PREFIX + "tileset.json")
        assert status == 200, body
        cls.packed_tileset_headers = headers
        cls.packed_tileset_body = body
        cls.packed_tileset = assemble(cls.daemon, "tileset.json")
        cls.packed_tiles = list(walk(cls.packed_tileset["root"]))
        cls.packed_glbs = {}
        for tile, _, _ in cls.packed_tiles:
            uri = tile["content"]["uri"]
            status, headers, body = cls.daemon.request("GET", PREFIX + uri)
            assert status == 200, (uri, status, body[:200])
            assert headers["Content-Type"] == "model/gltf-binary", uri
            cls.packed_glbs[uri] = body

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            code = cls.daemon.stop()
            keep = code != 0
            cls.daemon.cleanup(keep=keep)
        shutil.rmtree(cls.glb_dir, ignore_errors=True)

    def test_tileset_is_3d_tiles_1_1(self):
        t = self.tileset
        self.assertEqual(t["asset"]["version"], "1.1")
        self.assertEqual(self.tileset_headers["Content-Type"], "application/json")
        self.assertEqual(self.tileset_headers["Access-Control-Allow-Origin"], "*")
        self.assertGreaterEqual(t["geometricError"], t["root"]["geometricError"])
        self.assertEqual(t["root"]["refine"], "REPLACE")
        status, _, model = self.daemon.get_json("/v1/models/" + MODEL)
        self.assertEqual(status, 200)
        self.assertEqual(len(self.tiles), model["patches"])
        keys = {key_of(tile["content"]["uri"]) for tile, _, _ in self.tiles}
        self.assertEqual(len(keys), len(self.tiles))
        # The content sits on the earth in ECEF: the root's vertices, through its transform, lie
        # 6350..6390 km from the earth's centre.
        root, world, _ = self.tiles[0]
        gltf, bin_chunk = decode_glb(self.glbs[root["content"]["uri"]])
        positions = read_accessor(gltf, bin_chunk,
                                  gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
        for v in range(0, len(positions), 3):
            x, y, z = positions[v:v + 3]
            self.assertTrue(6.35e6 < math.dist(apply(world, [x, -z, y]), [0, 0, 0]) < 6.39e6)
        print("\ntileset: %d tiles, %d bytes, %.3f s; %d GLBs, %d bytes, %.3f s"
              % (len(self.tiles), self.tileset_bytes, self.tileset_seconds, len(self.glbs),
                 sum(len(b) for b in self.glbs.values()), self.glb_seconds), file=sys.stderr)

    def test_geometric_error_falls_strictly_from_parent_to_child(self):
        for tile, _, parent in self.tiles:
            uri = tile["content"]["uri"]
            self.assertIn(tile.get("refine", "REPLACE"), ("REPLACE",))
            if "children" not in tile:
                self.assertEqual(tile["geometricError"], 0, uri)
            else:
                self.assertGreater(tile["geometricError"], 0, uri)
            if parent is not None:
                self.assertLess(tile["geometricError"], parent["geometricError"], uri)

    def test_children_volumes_lie_inside_their_parents(self):
        volumes = {}
        for tile, world, parent in self.tiles:
            volume = aabb(box_corners(tile["boundingVolume"]["box"], world))
            volumes[id(tile)] = volume
            if parent is not None:
                self.assertTrue(inside(volume, volumes[id(parent)]),
                                "%s not inside its parent" % tile["content"]["uri"])

    def test_every_uri_resolves_as_gltf_binary_with_an_etag(self):
        for uri, headers in self.glb_headers.items():
            self.assertEqual(headers["Content-Type"], "model/gltf-binary", uri)
            self.assertTrue(headers["ETag"].startswith('"'), uri)
            self.assertEqual(headers["Access-Control-Allow-Origin"], "*")
            self.assertIn("max-age", headers["Cache-Control"])

    def test_content_lies_inside_its_tile_volume_and_matches_the_grid(self):
        for tile, world, _ in self.tiles:
            uri = tile["content"]["uri"]
            gltf, bin_chunk = decode_glb(self.glbs[uri])
            self.assertEqual(gltf["asset"]["version"], "2.0")
            corners = box_corners(tile["boundingVolume"]["box"], world)
            lo, hi = aabb(corners)
            status, _, aara = self.daemon.request("GET", "/v1/models/%s/patches/%s/positions"
                                                  % (MODEL, key_of(uri)))
            self.assertEqual(status, 200)
            quads = complete_quads(aara)
            if "meshes" not in gltf:
                self.assertEqual(quads, 0, uri)
                continue
            primitive = gltf["meshes"][0]["primitives"][0]
            self.assertEqual(primitive.get("mode", 4), 4)
            accessors = [primitive["attributes"]["POSITION"], primitive["attributes"]["NORMAL"],
                         primitive["attributes"]["TEXCOORD_0"], primitive["indices"]]
            data = [read_accessor(gltf, bin_chunk, a) for a in accessors]
            for index, values in zip(accessors, data):
                accessor = gltf["accessors"][index]
                width = WIDTH[accessor["type"]]
                for c in range(width):
                    column = values[c::width]
                    self.assertEqual(accessor["min"][c], min(column), (uri, index))
                    self.assertEqual(accessor["max"][c], max(column), (uri, index))
            positions, _, _, indices = data
            count = len(positions) // 3
            self.assertEqual(len(indices), 6 * quads, uri)
            self.assertLess(max(indices), count)
            self.assertEqual(len(set(indices)), count, "%s stores unused vertices" % uri)
            for v in range(count):
                x, y, z = positions[v * 3:v * 3 + 3]
                # glTF y-up -> 3D Tiles z-up: (x, y, z) -> (x, -z, y), then the tile transform.
                p = apply(world, [x, -z, y])
                self.assertTrue(all(lo[i] <= p[i] <= hi[i] for i in range(3)),
                                "%s vertex %d %r outside %r..%r" % (uri, v, p, lo, hi))

    def test_every_glb_passes_the_khronos_validator(self):
        """Both tilesets' content: the compressed GLBs (the default) and the float32 ones."""
        paths = []
        for suffix, glbs in (("", self.packed_glbs), ("-raw", self.glbs)):
            for uri, body in glbs.items():
                path = os.path.join(self.glb_dir, key_of(uri) + suffix + ".glb")
                with open(path, "wb") as f:
                    f.write(body)
                paths.append(path)
        self.assertEqual(len(paths), 2 * len(self.tiles))
        start = time.monotonic()
        result = subprocess.run(["node", ARGS.validator, ARGS.node_tools, *paths],
                                capture_output=True, text=True, timeout=600)
        seconds = time.monotonic() - start
        self.assertEqual(result.returncode, 0, result.stderr)
        reports = [json.loads(line) for line in result.stdout.splitlines() if line.strip()]
        # One report per file, and one more per compressed GLB with a mesh: its data decoded by
        # meshoptimizer's JavaScript decoder and validated as a plain GLB (validate_gltf.js).
        with_mesh = sum(1 for body in self.packed_glbs.values() if "meshes" in decode_glb(body)[0])
        self.assertGreater(with_mesh, 0)
        self.assertEqual(len(reports), len(paths) + with_mesh)
        self.assertEqual(sum(1 for r in reports if r["file"].endswith("#decoded")), with_mesh)
        failed = [r for r in reports if r["errors"] != 0]
        self.assertEqual(failed, [], "validator errors:\n" + "\n".join(
            "%s: %s" % (r["file"], "; ".join(r["messages"])) for r in failed[:5]))
        warnings = sum(r["warnings"] for r in reports)
        infos = sum(r["infos"] for r in reports)
        print("\ngltf-validator %s: %d GLBs, 0 errors, %d warnings, %d infos, %.1f s"
              % (reports[0]["validator"], len(reports), warnings, infos, seconds),
              file=sys.stderr)
        examples = [m for r in reports for m in r["messages"]][:5]
        if examples:
            print("  e.g. " + "\n  e.g. ".join(examples), file=sys.stderr)

    def test_the_default_tileset_names_compressed_content_inside_the_same_volumes(self):
        raw = {key_of(t["content"]["uri"]): (t, w) for t, w, _ in self.tiles}
        self.assertEqual(len(self.packed_tiles), len(self.tiles))
        packed_bytes = raw_bytes = 0
        for tile, world, _ in self.packed_tiles:
            uri = tile["content"]["uri"]
            self.assertNotIn("compress", uri)
            raw_tile, raw_world = raw[key_of(uri)]
            self.assertEqual(raw_tile["content"]["uri"], uri + "&compress=none")
            # The same tree: placement, volumes and errors as the raw tileset's.
            for field in ("transform", "boundingVolume", "geometricError"):
                self.assertEqual(tile[field], raw_tile[field], uri)
            gltf, bin_chunk = decode_glb(self.packed_glbs[uri])
            raw_gltf, _ = decode_glb(self.glbs[raw_tile["content"]["uri"]])
            packed_bytes += len(self.packed_glbs[uri])
            raw_bytes += len(self.glbs[raw_tile["content"]["uri"]])
            if "meshes" not in raw_gltf:
                self.assertNotIn("meshes", gltf, uri)
                continue
            self.assertEqual(gltf["extensionsRequired"],
                             ["EXT_meshopt_compression", "KHR_mesh_quantization"], uri)
            self.assertEqual(gltf["buffers"][1]["extensions"]["EXT_meshopt_compression"],
                             {"fallback": True}, uri)
            self.assertNotIn("uri", gltf["buffers"][1])
            primitive = gltf["meshes"][0]["primitives"][0]
            raw_primitive = raw_gltf["meshes"][0]["primitives"][0]
            for semantic in ("POSITION", "NORMAL", "TEXCOORD_0"):
                self.assertEqual(gltf["accessors"][primitive["attributes"][semantic]]["count"],
                                 raw_gltf["accessors"][raw_primitive["attributes"][semantic]]
                                 ["count"], (uri, semantic))
                view = gltf["bufferViews"][gltf["accessors"][primitive["attributes"][semantic]]
                                           ["bufferView"]]
                self.assertIn("EXT_meshopt_compression", view["extensions"], (uri, semantic))
            self.assertEqual(gltf["accessors"][primitive["indices"]]["count"],
                             raw_gltf["accessors"][raw_primitive["indices"]]["count"], uri)
            # The quantized range through the node's translation and scale, glTF's y-up -> z-up
            # and the tile's transform lies inside the tile's volume.
            position = gltf["accessors"][primitive["attributes"]["POSITION"]]
            self.assertEqual(position["componentType"], 5123)
            node = gltf["nodes"][0]
            t, s = node["translation"], node["scale"]
            lo, hi = aabb(box_corners(tile["boundingVolume"]["box"], world))
            for qx in (position["min"][0], position["max"][0]):
                for qy in (position["min"][1], position["max"][1]):
                    for qz in (position["min"][2], position["max"][2]):
                        x, y, z = (t[0] + s[0] * qx, t[1] + s[1] * qy, t[2] + s[2] * qz)
                        p = apply(world, [x, -z, y])
                        self.assertTrue(all(lo[i] <= p[i] <= hi[i] for i in range(3)),
                                        "%s corner %r outside %r..%r" % (uri, p, lo, hi))
        self.assertLess(packed_bytes, raw_bytes)
        print("\ncompressed tileset: %d GLBs, %d bytes (float32: %d bytes, %.2f)"
              % (len(self.packed_glbs), packed_bytes, raw_bytes, packed_bytes / raw_bytes),
              file=sys.stderr)

    def test_external_tilesets_put_together_give_the_one_document_tree(self):
        def canonical(tileset):
            return [(tile["content"]["uri"], tile["geometricError"], tile.get("refine"),
                     aabb(box_corners(tile["boundingVolume"]["box"], world)),
                     [c["content"]["uri"] for c in tile.get("children", [])])
                    for tile, world, _ in walk(tileset["root"])]

        whole_docs, split_docs = [], []
        whole = assemble(self.daemon, RAW_TILESET + "&levels=16", whole_docs)
        split = assemble(self.daemon, RAW_TILESET + "&levels=1", split_docs)
        self.assertEqual(len(whole_docs), 1)  # the model is shallower than 16 levels
        self.assertEqual(canonical(split), canonical(whole))
        self.assertEqual(canonical(self.tileset), canonical(whole))
        status, _, model = self.daemon.get_json("/v1/models/" + MODEL)
        # One document per patch with children: its tile and, as GLBs or external tiles, its
        # children's.
        parents = sum(1 for tile, _, _ in walk(whole["root"]) if "children" in tile)
        self.assertEqual(len(split_docs), parents)
        self.assertEqual(len(list(walk(whole["root"]))), model["patches"])
        for uri, doc in split_docs:
            root = doc["root"]
            self.assertEqual(doc["asset"]["version"], "1.1")
            self.assertEqual(doc["asset"]["extras"]["model_version"], model["version"], uri)
            self.assertEqual(root["refine"], "REPLACE")
            if "root=" in uri:  # an external tileset: placed by the tile naming it
                self.assertEqual(root["transform"][12:15], [0, 0, 0], uri)
            for child in root.get("children", []):
                self.assertNotIn("children", child, uri)
                child_uri = child["content"]["uri"]
                if is_external(child):
                    params = dict(p.partition("=")[::2] for p in child_uri.partition("?")[2].split("&"))
                    self.assertEqual(params, {"root": params["root"], "v": str(model["version"]),
                                              "levels": "1", "compress": "none"}, child_uri)

    def test_external_tileset_parameters_are_checked(self):
        for query, expected in (("levels=0", 400), ("levels=17", 400), ("levels=x", 400),
                                ("root=x_1", 400), ("root=30_0_0", 404), ("root=0_0_0&v=99999", 404)):
            status, _, body = self.daemon.request("GET", PREFIX + "tileset.json?" + query)
            self.assertEqual(status, expected, (query, body[:200]))
            self.assertIn("error", json.loads(body), query)

    def test_tileset_json_is_gzipped_once_when_accepted_with_vary(self):
        plain = self.packed_tileset_body
        self.assertIsNone(self.packed_tileset_headers.get("Content-Encoding"))
        self.assertEqual(self.packed_tileset_headers["Vary"], "Accept-Encoding")
        status, _, before = self.daemon.get_json("/v1/stats")
        status, headers, body = self.daemon.request(
            "GET", PREFIX + "tileset.json", headers={"Accept-Encoding": "gzip, deflate"})
        self.assertEqual(status, 200)
        self.assertEqual(headers["Content-Encoding"], "gzip")
        self.assertEqual(headers["Vary"], "Accept-Encoding")
        self.assertEqual(headers["Content-Type"], "application/json")
        self.assertEqual(int(headers["Content-Length"]), len(body))
        self.assertNotEqual(headers["ETag"], self.packed_tileset_headers["ETag"])
        self.assertEqual(gzip.decompress(body), plain)
        self.assertLess(len(body) * 4, len(plain))
        # Made once: the second request is a cache hit with the same bytes, no miss.
        status, _, middle = self.daemon.get_json("/v1/stats")
        self.assertGreater(middle["memory"]["encoded_bytes_by_encoding"]["json_gzip"], 0)
        status, headers2, body2 = self.daemon.request(
            "GET", PREFIX + "tileset.json", headers={"Accept-Encoding": "gzip"})
        status, _, after = self.daemon.get_json("/v1/stats")
        self.assertEqual(body2, body)
        self.assertEqual(headers2["ETag"], headers["ETag"])
        self.assertEqual(after["cache"]["misses"], middle["cache"]["misses"])
        self.assertGreater(after["cache"]["hits"], middle["cache"]["hits"])
        self.assertGreater(middle["cache"]["misses"], before["cache"]["misses"])
        # Revalidation of the gzipped representation; q=0 refuses gzip.
        status, headers3, _ = self.daemon.request(
            "GET", PREFIX + "tileset.json",
            headers={"Accept-Encoding": "gzip", "If-None-Match": headers["ETag"]})
        self.assertEqual(status, 304)
        self.assertEqual(headers3["Vary"], "Accept-Encoding")
        status, headers4, body4 = self.daemon.request(
            "GET", PREFIX + "tileset.json", headers={"Accept-Encoding": "gzip;q=0"})
        self.assertIsNone(headers4.get("Content-Encoding"))
        self.assertEqual(body4, plain)
        # The raw tileset gzipped is its own body.
        status, headers5, body5 = self.daemon.request(
            "GET", PREFIX + RAW_TILESET, headers={"Accept-Encoding": "gzip"})
        self.assertEqual(headers5["Content-Encoding"], "gzip")
        self.assertEqual(json.loads(gzip.decompress(body5)), self.tileset_document)
        # A subtree's document, and other levels, are gzipped too (per request: they are small).
        for query in ("&levels=2", "&root=1_0_0"):
            status, headers6, body6 = self.daemon.request(
                "GET", PREFIX + RAW_TILESET + query, headers={"Accept-Encoding": "gzip"})
            self.assertEqual((status, headers6["Content-Encoding"]), (200, "gzip"), query)
            self.assertEqual(headers6["Vary"], "Accept-Encoding")
            status, _, plain6 = self.daemon.request("GET", PREFIX + RAW_TILESET + query)
            self.assertEqual(json.loads(gzip.decompress(body6)), json.loads(plain6), query)
        status, _, body = self.daemon.request("GET", PREFIX + "tileset.json?compress=zstd")
        self.assertEqual(status, 400)

    def test_etags_answer_304_and_head_has_no_body(self):
        uri = self.tiles[-1][0]["content"]["uri"]
        etag = self.glb_headers[uri]["ETag"]
        status, headers, body = self.daemon.request("GET", PREFIX + uri,
                                                    headers={"If-None-Match": etag})
        self.assertEqual(status, 304)
        self.assertEqual(body, b"")
        self.assertEqual(headers["ETag"], etag)
        etag = self.tileset_headers["ETag"]
        status, _, _ = self.daemon.request("GET", PREFIX + RAW_TILESET,
                                           headers={"If-None-Match": etag})
        self.assertEqual(status, 304)
        # The other tileset and the other encoding of the tile are other representations.
        self.assertNotEqual(self.packed_tileset_headers["ETag"], etag)
        status, _, _ = self.daemon.request("GET", PREFIX + "tileset.json",
                                           headers={"If-None-Match": etag})
        self.assertEqual(status, 200)
        status, headers, body = self.daemon.request("HEAD", PREFIX + uri)
        self.assertEqual(status, 200)
        self.assertEqual(body, b"")
        self.assertEqual(int(headers["Content-Length"]), len(self.glbs[uri]))
        # Same bytes on a second request (from the GLB cache).
        status, _, body = self.daemon.request("GET", PREFIX + uri)
        self.assertEqual(body, self.glbs[uri])

    def test_content_uris_name_the_version_of_their_patch(self):
        status, _, hierarchy = self.daemon.get_json("/v1/models/%s/hierarchy" % MODEL)
        self.assertEqual(status, 200)
        versions = {}
        nodes = [hierarchy["root"]]
        while nodes:
            node = nodes.pop()
            versions[node["key"]] = node["version"]
            nodes.extend(node.get("children", []))
        # The merge (vsm merge, before the daemon started) rewrote some patches: not all are at 1.
        self.assertGreater(max(versions.values()), 1)
        for tile, _, _ in self.tiles:
            uri = tile["content"]["uri"]
            self.assertEqual(version_of(uri), versions[key_of(uri)], uri)
            self.assertEqual(self.glb_headers[uri]["X-VSM-Patch-Version"],
                             str(versions[key_of(uri)]), uri)
        # Without ?v= the route answers the current version; a version the daemon does not serve
        # (newer than the model's) is 404 that no cache keeps, never another version's bytes.
        uri = self.tiles[0][0]["content"]["uri"]
        status, _, body = self.daemon.request("GET", PREFIX + key_of(uri) + ".glb?compress=none")
        self.assertEqual(status, 200)
        self.assertEqual(body, self.glbs[uri])
        status, headers, body = self.daemon.request(
            "GET", PREFIX + key_of(uri) + ".glb?v=12345&compress=none")
        self.assertEqual(status, 404, body[:300])
        self.assertEqual(headers["Cache-Control"], "no-store")
        self.assertEqual(json.loads(body)["error"]["code"], "not_found")

    def test_a_repeated_glb_is_a_cache_hit(self):
        uri = self.tiles[-1][0]["content"]["uri"]
        status, _, before = self.daemon.get_json("/v1/stats")
        self.assertEqual(status, 200)
        status, headers, body = self.daemon.request("GET", PREFIX + uri)
        self.assertEqual(status, 200)
        status, _, after = self.daemon.get_json("/v1/stats")
        self.assertEqual(body, self.glbs[uri])
        self.assertEqual(headers["ETag"], self.glb_headers[uri]["ETag"])
        # Encoded once (in setUpClass), answered from the cache since: a hit, no miss.
        self.assertGreater(after["cache"]["hits"], before["cache"]["hits"])
        self.assertEqual(after["cache"]["misses"], before["cache"]["misses"])
        self.assertGreaterEqual(after["memory"]["encoded_bytes_by_encoding"]["glb"], len(body))
        self.assertLessEqual(after["memory"]["resident_bytes"], after["memory"]["budget_bytes"])

    def test_unknown_tiles_and_models_are_json_errors(self):
        for path, expected in ((PREFIX + "29_0_0.glb", 404), (PREFIX + "abc.glb", 400),
                               ("/v1/models/nope/3dtiles/tileset.json", 404),
                               ("/v1/models/nope/3dtiles/0_0_0.glb", 404)):
            status, headers, body = self.daemon.request("GET", path)
            self.assertEqual(status, expected, path)
            self.assertIn("error", json.loads(body), path)

    def test_camera_lod_is_the_cut_a_renderer_draws(self):
        """GET /lod with a camera against a brute force over every tile of tileset.json: a tile
        is drawn when it and its ancestors are in the frustum (no box wholly outside one of its
        planes), its ancestors' screen-space errors exceed the threshold, and its own does not or
        it is a leaf (3D Tiles' REPLACE traversal, error = geometricError * height /
        (2 * distance * tan(fov / 2)), the distance the eye's to the box)."""
        tiles = {}
        for tile, world, parent in self.tiles:
            key = key_of(tile["content"]["uri"])
            tiles[key] = {"box": aabb(box_corners(tile["boundingVolume"]["box"], world)),
                          "error": tile["geometricError"], "leaf": "children" not in tile,
                          "parent": key_of(parent["content"]["uri"]) if parent else None}
        lo, hi = tiles["0_0_0"]["box"]
        centre = [(lo[i] + hi[i]) / 2 for i in range(3)]
        zenith = [c / math.dist(centre, [0, 0, 0]) for c in centre]
        east = normalise(cross([0, 0, 1], zenith))
        north = cross(zenith, east)
        width, height, fov = 1024, 768, 60.0
        cuts = set()
        for altitude in (2e3, 2e4, 2e5, 2e6):
            for tilt in (0.0, 0.6, 1.3):  # radians from straight down, looking north
                for sse in (2.0, 16.0, 64.0):
                    eye = [centre[i] + zenith[i] * altitude - north[i] * altitude * math.tan(tilt)
                           * 0.5 for i in range(3)]
                    direction = [north[i] * math.sin(tilt) - zenith[i] * math.cos(tilt)
                                 for i in range(3)]
                    up = north if tilt == 0.0 else zenith
                    expected = brute_force_cut(tiles, eye, direction, up, fov, width, height, sse)
                    query = ("eye=%r,%r,%r&dir=%r,%r,%r&up=%r,%r,%r&fov=%r&width=%d&height=%d"
                             "&sse=%r" % (*eye, *direction, *up, fov, width, height, sse))
                    status, _, body = self.daemon.get_json("/v1/models/%s/lod?%s" % (MODEL, query))
                    self.assertEqual(status, 200, body)
                    got = {p["key"]: p["screen_error"] for p in body["patches"]}
                    self.assertEqual(set(got), set(expected), query)
                    for key, error in expected.items():
                        self.assertAlmostEqual(got[key], error, delta=1e-6 * max(1.0, error))
                    self.assertEqual(body["camera"]["sse"], sse)
                    cuts.add(frozenset(got))
        # The views differ: the cut follows the camera.
        self.assertGreater(len(cuts), 10)
        for bad in ("eye=0,0,0&dir=1,0,0&up=2,0,0&fov=60&height=768&sse=16",
                    "eye=0,0,0&dir=1,0,0&up=0,0,1&fov=180&height=768&sse=16",
                    "eye=0,0,0&dir=1,0,0&up=0,0,1&fov=60&height=768",
                    "eye=0,0,0&dir=1,0,0&up=0,0,1&fov=60&height=768&sse=0",
                    "eye=0,0&dir=1,0,0&up=0,0,1&fov=60&height=768&sse=16",
                    "eye=0,0,0&dir=1,0,0&up=0,0,1&fov=60&height=768&sse=16&box=0,0,0,1,1,1"):
            status, _, body = self.daemon.get_json("/v1/models/%s/lod?%s" % (MODEL, bad))
            self.assertEqual(status, 400, bad)
            self.assertIn("error", body, bad)


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def normalise(v):
    n = math.sqrt(sum(c * c for c in v))
    return [c / n for c in v]


def brute_force_cut(tiles, eye, direction, up, fov, width, height, sse):
    """{key: screen-space error} of the tiles a REPLACE renderer draws, tile by tile from its
    definition (not by descending the tree)."""
    f = normalise(direction)
    r = normalise(cross(f, up))
    u = cross(r, f)
    tan_y = math.tan(math.radians(fov) / 2)
    tan_x = tan_y * width / height

    def outside(box):
        """Every corner behind the near plane, or beyond one side plane."""
        corners = [[box[(k >> i) & 1][i] for i in range(3)] for k in range(8)]
        rel = [[c[i] - eye[i] for i in range(3)] for c in corners]
        depth = [sum(p[i] * f[i] for i in range(3)) for p in rel]
        across = [sum(p[i] * r[i] for i in range(3)) for p in rel]
        above = [sum(p[i] * u[i] for i in range(3)) for p in rel]
        return (all(d < 0 for d in depth)
                or all(a > tan_x * d for a, d in zip(across, depth))
                or all(a < -tan_x * d for a, d in zip(across, depth))
                or all(a > tan_y * d for a, d in zip(above, depth))
                or all(a < -tan_y * d for a, d in zip(above, depth)))

    def error(tile):
        if tile["error"] == 0:
            return 0.0
        (lo, hi) = tile["box"]
        distance = math.dist(eye, [min(max(eye[i], lo[i]), hi[i]) for i in range(3)])
        return math.inf if distance == 0 else tile["error"] * height / (2 * distance * tan_y)

    out = {}
    for key, tile in tiles.items():
        if outside(tile["box"]) or not (error(tile) <= sse or tile["leaf"]):
            continue
        ancestor = tile["parent"]
        while ancestor is not None and not outside(tiles[ancestor]["box"]) \
                and error(tiles[ancestor]) > sse:
            ancestor = tiles[ancestor]["parent"]
        if ancestor is None:
            out[key] = error(tile)
    return out

def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--model", required=True, help="the merged OPC (copied into the data root)")
    parser.add_argument("--node-tools", required=True, help="prefix holding node_modules")
    parser.add_argument("--validator", required=True, help="validate_gltf.js")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
