#!/usr/bin/python3
"""A textured import of a real DEM with a real image, checked independently of vsm's code:

`vsm import jacksboro_fault_dem.tif <opc> --texture conus_visible_earth.tif --patch-size 65`
(the NASA Visible Earth image, georeferenced in EPSG:4326, covers the Jacksboro area), then with
our own XML and .aara readers and GDAL's Python bindings:

- every patch's Patch.xml names Coordinates.aara and Diffuse\\<folder>.tif exactly as OPC.md shows,
  and Images/Diffuse/<folder>.tif is an RGB(A) 8-bit tile of 64 x 64 texels;
- Coordinates.aara is V2f of the positions' size with values in [0, 1] (u = x / 64, v = y / 64 of
  the stored vertices, v = 0 the top row);
- leaf texels match the source image at their mapped position (DEM quad centre -> lon/lat ->
  image pixel, bilinear between pixel centres) within a tolerance;
- a parent texel is the mean of the 2 x 2 child texels it covers;
- `vsm validate` passes;
- with --vsmd: the real vsmd serves the root's GLB with the tile embedded as a PNG image and
  TEXCOORD_0 in [0, 1]; with --node-tools holding Khronos' gltf-validator (installed by the
  node-tools fixture), that GLB validates with zero errors.

Run by ctest:  texture_test.py --vsm build/server/cli/vsm --data ../shared/data --work <dir>"""

import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import unittest
import xml.etree.ElementTree as ET

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from check_import import read_hierarchy, read_tile  # noqa: E402
from harness import Daemon, bilinear, read_aara  # noqa: E402

gdal.UseExceptions()

def check_glb(test, opc):
    """The root's GLB from a real vsmd: texture embedded, coordinates in [0, 1], valid glTF."""
    root = tempfile.mkdtemp(prefix="vsm-texture-")
    shutil.copytree(opc, os.path.join(root, "jack"))
    daemon = Daemon(root=root, vsmd=ARGS.vsmd)
    try:
        # The default (meshopt-compressed) GLB and the uncompressed one.
        glbs = {}
        for query in ("", "?compress=none"):
            status, _, glbs[query] = daemon.request(
                "GET", "/v1/models/jack/3dtiles/0_0_0.glb%s" % query, timeout=60)
            test.assertEqual(status, 200, (query, status, glbs[query][:200]))
    finally:
        daemon.stop(timeout=30)
    for query, data in glbs.items():
        json_length = struct.unpack_from("<I", data, 12)[0]
        gltf = json.loads(data[20:20 + json_length])
        test.assertEqual(gltf["images"][0]["mimeType"], "image/png", gltf.get("images"))
        bin_start = 20 + json_length + 8
        view = gltf["bufferViews"][gltf["images"][0]["bufferView"]]
        png = data[bin_start + view.get("byteOffset", 0):][:8]
        test.assertEqual(png, b"\x89PNG\r\n\x1a\n", png)
        material = gltf["materials"][0]["pbrMetallicRoughness"]
        test.assertEqual(material["baseColorTexture"]["index"], 0)
        uv = gltf["accessors"][gltf["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
        if query:
            test.assertTrue(min(uv["min"]) >= 0 and max(uv["max"]) <= 1, uv)
        else:
            # Compressed: UNSIGNED_SHORT normalized, so in [0, 1] by construction.
            test.assertTrue(uv["componentType"] == 5123 and uv["normalized"], uv)
            test.assertIn("EXT_meshopt_compression", gltf["extensionsRequired"], gltf)
    validator = os.path.join(ARGS.node_tools or "", "node_modules", "gltf-validator")
    if ARGS.validator and os.path.isdir(validator) and shutil.which("node"):
        paths = []
        for query, data in glbs.items():
            glb = os.path.join(root, "0_0_0%s.glb" % ("-raw" if query else ""))
            with open(glb, "wb") as f:
                f.write(data)
            paths.append(glb)
        out = subprocess.run(["node", ARGS.validator, ARGS.node_tools, *paths], check=True,
                             capture_output=True, text=True).stdout
        for line in out.splitlines():
            report = json.loads(line)
            test.assertEqual(report["errors"], 0, report)
        print("texture: textured GLBs (compressed and not) valid (gltf-validator %s)"
              % report["validator"])
    shutil.rmtree(root, ignore_errors=True)


ARGS = None


class Texture(unittest.TestCase):
    def test_a_textured_import(self):
        """Files and XML as OPC.md says, coordinates, leaf texels against the image, parents as
        2 x 2 means, vsm validate; the GLB from vsmd."""
        dem_path = os.path.join(ARGS.data, "jacksboro_fault_dem.tif")
        image_path = os.path.join(ARGS.data, "conus_visible_earth.tif")
        opc = os.path.join(ARGS.work, "jacksboro-textured")
        shutil.rmtree(ARGS.work, ignore_errors=True)
        os.makedirs(ARGS.work)
        harness.import_dem(dem_path, opc, 65, "--texture", image_path)
        self.assertEqual(sorted(os.listdir(ARGS.work)), ["jacksboro-textured"], os.listdir(ARGS.work))

        dem = gdal.Open(dem_path)
        dem_gt = dem.GetGeoTransform()
        img = gdal.Open(image_path)
        img_gt = img.GetGeoTransform()
        inv = gdal.InvGeoTransform(img_gt)
        image = img.ReadAsArray()  # (bands, rows, cols)
        n = 65
        tile_size = n - 1

        _, root_folder, children = read_hierarchy(opc)
        folders = [root_folder] + [c for kids in children.values() for c in kids.values()]

        tiles = {}
        leaf_checks = 0
        worst = 0.0
        for folder in folders:
            patch = ET.parse(os.path.join(opc, "Patches", folder, "Patch.xml")).getroot().find("Patch")
            coords_name = patch.find("Coordinates/DiffuseColor1Coordinates").text
            texture_name = patch.find("Textures/DiffuseColor1Texture").text
            self.assertEqual(coords_name, "Coordinates.aara", coords_name)
            self.assertEqual(texture_name, "Diffuse\\%s.tif" % folder, texture_name)
            texture_file = os.path.join(opc, "Images", "Diffuse", folder + ".tif")
            self.assertTrue(os.path.isfile(texture_file), texture_file)

            _, psizes, _ = read_aara(os.path.join(opc, "Patches", folder, "Positions.aara"))
            ctype, csizes, uv = read_aara(os.path.join(opc, "Patches", folder, coords_name))
            self.assertEqual(ctype, "V2f", (folder, ctype))
            self.assertEqual(csizes, psizes, (folder, csizes, psizes))
            self.assertTrue(np.all(uv >= 0) and np.all(uv <= 1), folder)
            ox, oy = [int(float(v)) for v in
                      patch.find("Vsm/Offset").text.strip("[]").split(",")]
            cols = np.arange(csizes[0]) + ox
            rows = np.arange(csizes[1]) + oy
            self.assertTrue(np.allclose(uv[:, :, 0], cols[None, :] / (n - 1), atol=1e-6), folder)
            self.assertTrue(np.allclose(uv[:, :, 1], rows[:, None] / (n - 1), atol=1e-6), folder)

            ds = gdal.Open(texture_file)
            self.assertEqual((ds.RasterXSize, ds.RasterYSize), (tile_size, tile_size), folder)
            self.assertIn(ds.RasterCount, (3, 4), ds.RasterCount)
            self.assertTrue(all(ds.GetRasterBand(b + 1).DataType == gdal.GDT_Byte
                       for b in range(ds.RasterCount)))
            tiles[folder] = read_tile(texture_file)

            depth, kx, ky = [int(v) for v in folder.split("_")]
            if folder not in children:  # a leaf: texels against the source image
                span = tile_size  # leaves are the bottom level: one texel per DEM quad
                for (i, j) in [(0, 0), (5, 7), (31, 32), (63, 0), (17, 63), (40, 22)]:
                    sx = kx * span + i + 0.5  # quad centre in DEM sample coordinates
                    sy = ky * span + j + 0.5
                    if sx > dem.RasterXSize - 1 or sy > dem.RasterYSize - 1:
                        continue  # beyond the DEM's last sample
                    lon = dem_gt[0] + (sx + 0.5) * dem_gt[1]
                    lat = dem_gt[3] + (sy + 0.5) * dem_gt[5]
                    ix = inv[0] + lon * inv[1] + lat * inv[2]
                    iy = inv[3] + lon * inv[4] + lat * inv[5]
                    expected = bilinear(image, ix, iy)[:3]
                    got = tiles[folder][:3, j, i]
                    worst = max(worst, float(np.max(np.abs(got - expected))))
                    self.assertTrue(np.all(np.abs(got - expected) <= 1.5), (folder, i, j, got, expected))
                    leaf_checks += 1

        # Parents: each texel the mean of the 2 x 2 child texels it covers (quadrants nw ne sw se).
        parent_checks = 0
        for parent, kids in children.items():
            for q, child in kids.items():
                qx = 1 if q in ("ne", "se") else 0
                qy = 1 if q in ("sw", "se") else 0
                c = tiles[child]
                mean = (c[:, 0::2, 0::2] + c[:, 0::2, 1::2] + c[:, 1::2, 0::2] + c[:, 1::2, 1::2]) / 4
                half = tile_size // 2
                got = tiles[parent][:, qy * half:(qy + 1) * half, qx * half:(qx + 1) * half]
                self.assertTrue(np.all(np.abs(got - mean) <= 0.5 + 1e-9), (parent, child))
                parent_checks += 1

        self.assertGreaterEqual(leaf_checks, 20, leaf_checks)
        harness.vsm("validate", opc, check=True)
        if ARGS.vsmd:
            check_glb(self, opc)
        print("texture: %d patches, %d leaf texels within %.2f of the image, %d parent quadrants "
              "exact" % (len(folders), leaf_checks, worst, parent_checks))


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    parser.add_argument("--vsmd")
    parser.add_argument("--node-tools")
    parser.add_argument("--validator")
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
