#!/usr/bin/python3
"""End-to-end tests of the `vsm` command: clear errors for bad input, nothing half-written, and
`vsm validate` reporting each deliberate break in a copy of a real model.

Run by ctest with Debian's python3 (python3-gdal for making test rasters)."""

import argparse
import glob
import os
import pty
import re
import shutil
import struct
import subprocess
import sys
import unittest

import numpy as np
from osgeo import gdal

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import harness  # noqa: E402
from check_import import Failures, check_pro3d, find_ci, read_hierarchy  # noqa: E402
from harness import vsm, write_raster  # noqa: E402

gdal.UseExceptions()
ARGS = None


def work(name):
    path = os.path.join(ARGS.work, name)
    shutil.rmtree(path, ignore_errors=True)
    return path


class CliErrors(unittest.TestCase):
    def assert_one_line_error(self, result, *fragments):
        self.assertEqual(result.returncode, 1, result.stderr)
        lines = result.stderr.strip().splitlines()
        self.assertEqual(len(lines), 1, result.stderr)
        self.assertTrue(lines[0].startswith("vsm: error: "), lines[0])
        for fragment in fragments:
            self.assertIn(fragment, lines[0])

    def test_help_lists_the_commands(self):
        result = vsm("help")
        self.assertEqual(result.returncode, 0)
        for command in ("import", "info", "validate"):
            self.assertIn(command, result.stdout)

    def test_unknown_command_is_a_usage_error(self):
        result = vsm("frobnicate")
        self.assertEqual(result.returncode, 2)
        self.assertIn("unknown command", result.stderr)

    def test_merge_keeps_at_least_two_revisions(self):
        for bad in ("1", "0", "x", ""):
            result = vsm("merge", "a", "b", "--keep-revisions", bad)
            self.assertEqual(result.returncode, 2, result.stderr)
            self.assertIn("--keep-revisions must be an integer from 2 to 10000", result.stderr)

    def test_import_of_a_missing_file_fails_cleanly(self):
        out = work("missing-out")
        result = vsm("import", "/nonexistent/dem.tif", out)
        self.assert_one_line_error(result, "/nonexistent/dem.tif")
        self.assertFalse(os.path.exists(out))

    def test_import_of_a_file_that_is_no_raster_fails_cleanly(self):
        path = os.path.join(ARGS.work, "not-a-raster.tif")
        with open(path, "w") as f:
            f.write("this is not a GeoTIFF\n")
        out = work("garbage-out")
        self.assert_one_line_error(vsm("import", path, out), "not-a-raster.tif")
        self.assertFalse(os.path.exists(out))
        self.assertEqual([e for e in os.listdir(ARGS.work) if "garbage-out" in e], [])

    def test_import_of_a_raster_without_crs_is_rejected(self):
        path = os.path.join(ARGS.work, "no-crs.tif")
        write_raster(path, np.full((4, 4), 1.0), 10.0, 47.0, 0.01, epsg=None)
        out = work("no-crs-out")
        self.assert_one_line_error(vsm("import", path, out), "coordinate reference system")
        self.assertFalse(os.path.exists(out))

    def test_import_of_an_all_nodata_raster_is_rejected(self):
        path = os.path.join(ARGS.work, "all-nodata.tif")
        write_raster(path, np.full((4, 4), -9999.0), 10.0, 47.0, 0.01, nodata=-9999.0)
        out = work("all-nodata-out")
        result = vsm("import", path, out)
        self.assertEqual(result.returncode, 1, result.stderr)
        self.assertIn("vsm: error:", result.stderr)
        self.assertFalse(os.path.exists(out))

    def test_import_never_overwrites_an_existing_directory(self):
        out = work("existing")
        os.makedirs(out)
        marker = os.path.join(out, "keep.txt")
        with open(marker, "w") as f:
            f.write("mine")
        result = vsm("import", os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), out)
        self.assert_one_line_error(result, "exists")
        self.assertEqual(os.listdir(out), ["keep.txt"])

    def test_a_patch_size_that_is_not_a_power_of_two_plus_one_is_refused(self):
        out = work("bad-size")
        result = vsm("import", os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), out,
                     "--patch-size", "100")
        self.assertNotEqual(result.returncode, 0)
        self.assertIn("2^n+1", result.stderr)
        self.assertFalse(os.path.exists(out))

    def test_texels_per_quad_must_be_a_power_of_two_with_a_texture(self):
        dem = os.path.join(ARGS.data, "jacksboro_fault_dem.tif")
        out = work("bad-texels")
        for value in ("3", "0", "-4", "x", "8192"):
            result = vsm("import", dem, out, "--patch-size", "65", "--texels-per-quad", value)
            self.assertEqual(result.returncode, 2, (value, result.stderr))
            self.assertIn("power of two", result.stderr)
            self.assertFalse(os.path.exists(out), value)
        # No texture takes no texels.
        result = vsm("import", dem, out, "--patch-size", "65", "--texels-per-quad", "2",
                     "--texture", "none")
        self.assertEqual(result.returncode, 2, result.stderr)
        self.assertIn("--texels-per-quad needs a texture", result.stderr)
        self.assertFalse(os.path.exists(out))
        # 4096 is a power of two, but its tiles (64 x 4096 texels) exceed the cap.
        result = vsm("import", dem, out, "--patch-size", "65", "--texels-per-quad", "4096")
        self.assert_one_line_error(result, "texels per quad", "4096")
        self.assertFalse(os.path.exists(out))

    def test_info_of_a_directory_without_opc_fails_cleanly(self):
        out = work("empty-dir")
        os.makedirs(out)
        self.assert_one_line_error(vsm("info", out))

    def test_a_missing_vsm_heavy_is_one_line_naming_it(self):
        # vsm execs vsm-heavy from its own directory for the commands that need GDAL, PCL or
        # OpenImageIO: a vsm copied alone says so in one line.
        lone = work("lone")
        os.makedirs(lone)
        shutil.copy2(ARGS.vsm, lone)
        for command in (["import", "in.tif", "out"], ["merge", "a", "b"],
                        ["render-lod", "a", "a.png"]):
            result = subprocess.run([os.path.join(lone, "vsm"), *command], capture_output=True,
                                    text=True, timeout=60)
            self.assert_one_line_error(result, command[0] + " needs",
                                       os.path.join(lone, "vsm-heavy"), "missing")


class StartUp(unittest.TestCase):
    """help, info and validate load neither GDAL, PCL nor OpenImageIO (~300 libraries that took
    ld.so 0.1-1.5 s per start: tests/bench/startup_bench.sh)."""

    @classmethod
    def setUpClass(cls):
        cls.model = work("prism-startup")
        result = vsm("import", os.path.join(ARGS.data, "PRISMelevation.tif"), cls.model)
        assert result.returncode == 0, result.stderr

    def loaded_libraries(self, *args):
        """The shared objects ld.so maps for `vsm args` (LD_DEBUG=files, dlopen included)."""
        result = subprocess.run([ARGS.vsm, *args], capture_output=True, text=True, timeout=60,
                                env=dict(os.environ, LD_DEBUG="files"))
        self.assertEqual(result.returncode, 0, result.stderr)
        return re.findall(r"file=(\S+) \[\d+\];\s+generating link map", result.stderr)

    def test_help_info_and_validate_load_only_the_runtime_and_pugixml(self):
        for args in (["--help"], ["info", self.model], ["validate", self.model]):
            libraries = self.loaded_libraries(*args)
            if any(re.match(r"lib(asan|tsan|ubsan)\.", name) for name in libraries):
                self.skipTest("a sanitizer build links without --as-needed")
            heavy = [name for name in libraries if re.match(r"lib(gdal|pcl_|OpenImageIO)", name)]
            self.assertEqual(heavy, [], "vsm %s loads %s" % (args[0], heavy))
            self.assertLessEqual(len(libraries), 10, "vsm %s loads %s" % (args[0], libraries))


class ImageModule(unittest.TestCase):
    """OpenImageIO is linked by no binary: libvsm_image.so is loaded on the first texture image
    (core/opc/image_codec.hpp), so it costs only the commands that read or write one."""

    def test_no_binary_links_openimageio(self):
        heavy = os.path.join(os.path.dirname(ARGS.vsm), "vsm-heavy")
        for binary in (ARGS.vsm, heavy):
            result = subprocess.run(["ldd", binary], capture_output=True, text=True, timeout=60)
            self.assertEqual(result.returncode, 0, result.stderr)
            self.assertNotIn("libOpenImageIO", result.stdout, binary)

    def loaded_libraries(self, *args, env=None):
        result = subprocess.run(
            [ARGS.vsm, *args], capture_output=True, text=True, timeout=600,
            env=dict(env or os.environ, LD_DEBUG="files"))
        self.assertEqual(result.returncode, 0, result.stderr[-2000:])
        return re.findall(r"file=(\S+) \[\d+\];\s+generating link map", result.stderr)

    def test_an_import_writes_its_tiles_without_it_and_a_rendering_loads_it(self):
        raster = os.path.join(ARGS.data, "jacksboro_fault_dem.tif")
        models = {}
        for texture in (None, "none"):
            out = models[texture] = work("module-%s" % texture)
            extra = ["--texture", texture] if texture else []
            loaded = self.loaded_libraries("import", raster, out, "--patch-size", "65", *extra)
            self.assertFalse(any("libvsm_image.so" in name for name in loaded), texture)
            self.assertFalse(any("libOpenImageIO" in name for name in loaded), texture)
            # Tiles are TIFFs written with libtiff (core/opc/tiff_tile.cpp): one per patch.
            tiles = glob.glob(os.path.join(out, "Images", "Diffuse", "*.tif"))
            self.assertEqual(len(tiles) > 0, texture is None, texture)
        # Reading the tiles back (to render them) is what loads the module.
        picture = os.path.join(work("module-lod"), "lod.png")
        os.makedirs(os.path.dirname(picture))
        loaded = self.loaded_libraries("render-lod", models[None], picture, "--size", "64")
        self.assertTrue(any("libvsm_image.so" in name for name in loaded))
        self.assertTrue(any("libOpenImageIO" in name for name in loaded))
        self.assertTrue(os.path.getsize(picture) > 0)

    def test_a_missing_module_is_one_line_naming_it_and_writes_nothing(self):
        model = work("module-missing-model")
        imported = vsm("import", os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), model,
                       "--patch-size", "65")
        self.assertEqual(imported.returncode, 0, imported.stderr)
        picture = os.path.join(work("module-missing"), "lod.png")
        os.makedirs(os.path.dirname(picture))
        missing = work("no-such-dir") + "/libvsm_image.so"
        result = subprocess.run(
            [ARGS.vsm, "render-lod", model, picture, "--size", "64"],
            capture_output=True, text=True, timeout=600,
            env=dict(os.environ, VSM_IMAGE_MODULE=missing))
        self.assertEqual(result.returncode, 1, result.stderr)
        lines = result.stderr.strip().splitlines()
        errors = [line for line in lines if line.startswith("vsm: error: ")]
        self.assertEqual(errors, lines[-1:], result.stderr)
        self.assertIn(missing, errors[0])
        self.assertIn("VSM_IMAGE_MODULE", errors[0])
        self.assertFalse(os.path.exists(picture))


class ValidateFindsEachBreak(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.good = work("jacksboro-good")
        result = vsm("import", os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), cls.good,
                     "--patch-size", "33")
        assert result.returncode == 0, result.stderr

    def broken_copy(self, name):
        path = work(name)
        shutil.copytree(self.good, path)
        return path

    def test_our_own_output_is_valid(self):
        result = vsm("validate", self.good)
        self.assertEqual(result.returncode, 0, result.stdout + result.stderr)

    def test_info_describes_the_levels(self):
        result = vsm("info", self.good)
        self.assertEqual(result.returncode, 0, result.stderr)
        self.assertRegex(result.stdout, r"patch size\s+33 x 33")
        self.assertRegex(result.stdout, r"depth\s+\d+")

    def test_three_breaks_give_three_findings(self):
        opc = self.broken_copy("jacksboro-broken")
        patches, root, children = read_hierarchy(opc)

        # 1. A parent vertex that no longer equals its child's: shift the first defined vertex of
        #    the root patch by 50 m in its stored float32 local coordinates.
        root_positions = find_ci(os.path.join(patches, root), "Positions.aara")
        with open(root_positions, "r+b") as f:
            data = bytearray(f.read())
            n = data[0]
            offset = 1 + n + 1 + 8
            while True:
                x, y, z = struct.unpack_from("<3f", data, offset)
                if x == x:
                    break
                offset += 12
            struct.pack_into("<f", data, offset + 8, z + 50.0)
            f.seek(0)
            f.write(data)

        # 2. A leaf whose stored box does not match its vertices.
        leaves = [c for cs in children.values() for c in cs.values() if c not in children]
        leaf_box = leaves[0]
        patch_xml = find_ci(os.path.join(patches, leaf_box), "Patch.xml")
        text = open(patch_xml).read()
        text = re.sub(r"<GlobalBoundingBox>\[\[([-0-9.e]+)",
                      lambda m: "<GlobalBoundingBox>[[%r" % (float(m.group(1)) - 500.0), text)
        open(patch_xml, "w").write(text)

        # 3. Another leaf's positions truncated.
        leaf_cut = leaves[-1]
        cut = find_ci(os.path.join(patches, leaf_cut), "Positions.aara")
        size = os.path.getsize(cut)
        os.truncate(cut, size - 5)

        result = vsm("validate", opc)
        self.assertEqual(result.returncode, 1, result.stdout)
        findings = [l for l in result.stdout.splitlines() if ":" in l and "finding" not in l]
        for patch in (root, leaf_box, leaf_cut):
            self.assertTrue(any(patch in l for l in findings),
                            "no finding names %s in:\n%s" % (patch, result.stdout))

    def test_a_hierarchy_naming_a_missing_folder_is_reported(self):
        opc = self.broken_copy("jacksboro-missing-folder")
        patches, root, children = read_hierarchy(opc)
        leaf = [c for cs in children.values() for c in cs.values() if c not in children][0]
        shutil.rmtree(os.path.join(patches, leaf))
        result = vsm("validate", opc)
        self.assertEqual(result.returncode, 1)
        self.assertIn(leaf, result.stdout)
        info = vsm("info", opc)
        self.assertEqual(info.returncode, 1)
        self.assertIn(leaf, info.stderr)


class Pro3dComplete(unittest.TestCase):
    """Every import is complete for PRo3D (Images/, Coordinates.aara and a tile per patch) unless
    `--texture none` asks otherwise, which vsm warns about; such a model still validates."""

    def test_the_default_import_is_complete_for_pro3d(self):
        out = work("jacksboro-relief")
        result = vsm("import", os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), out,
                     "--patch-size", "33")
        self.assertEqual(result.returncode, 0, result.stderr)
        self.assertNotIn("PRo3D", result.stderr)
        failures = Failures()
        self.assertGreater(check_pro3d(out, failures), 20)
        self.assertEqual(failures.items, [])

    def test_texture_none_warns_on_stderr_and_writes_no_texture(self):
        out = work("jacksboro-bare")
        result = vsm("import", os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), out,
                     "--patch-size", "33", "--texture", "none")
        self.assertEqual(result.returncode, 0, result.stderr)
        self.assertRegex(result.stderr, r"--texture none.*PRo3D will not open it")
        self.assertFalse(os.path.exists(os.path.join(out, "Images")))
        patches, root, _ = read_hierarchy(out)
        self.assertNotIn("Coordinates.aara", os.listdir(os.path.join(patches, root)))
        failures = Failures()
        check_pro3d(out, failures)
        self.assertEqual(failures.count, 1, failures.items)  # the check does tell
        # A model without Images/ (as foreign OPCs may be) is still valid and readable.
        self.assertEqual(vsm("validate", out).returncode, 0)
        self.assertEqual(vsm("info", out).returncode, 0)

    def test_help_states_the_relief_light_and_none(self):
        text = vsm("help").stdout
        for fragment in ("shaded relief", "azimuth 315", "altitude 45", "--texture <image>|none",
                         "no vertical", "PRo3D"):
            self.assertIn(fragment, re.sub(r"\s+", " ", text))


class Progress(unittest.TestCase):
    """Long commands draw one updating line on a terminal and print plain lines otherwise."""

    def test_without_a_terminal_progress_is_a_line_per_ten_percent(self):
        out = work("progress-plain")
        result = vsm("import", os.path.join(ARGS.data, "PRISMelevation.tif"), out,
                     "--patch-size", "65")
        self.assertEqual(result.returncode, 0, result.stderr)
        self.assertNotIn("\r", result.stderr)
        self.assertNotIn("\x1b", result.stderr)
        self.assertEqual(result.stderr.splitlines(),
                         ["import %d%%" % p for p in range(0, 101, 10)])

    def run_on_terminal(self, *args):
        """(exit code, stdout, stderr bytes) of `vsm args` with stderr on a pseudo-terminal."""
        master, slave = pty.openpty()
        process = subprocess.Popen([ARGS.vsm, *args], stdin=subprocess.DEVNULL,
                                   stdout=subprocess.PIPE, stderr=slave)
        os.close(slave)
        terminal = b""
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # EIO: the other side is closed
                break
            if not chunk:
                break
            terminal += chunk
        os.close(master)
        stdout = process.stdout.read()
        process.stdout.close()
        return process.wait(timeout=600), stdout, terminal.decode()

    def assert_one_updating_line(self, terminal, last):
        # The terminal turns the final "\n" into "\r\n"; before it, nothing but redraws.
        self.assertTrue(terminal.endswith("\r\n"), repr(terminal[-80:]))
        # Log lines erase the progress line they land on ("\r" + erase to the end of the line)
        # and end with a newline; the progress is redrawn after them.
        logs = re.findall(r"\r\x1b\[K\d{4}-\d\d-\d\dT[^\r\n]*\r\n", terminal)
        body = terminal[:-2]
        for line in logs:
            body = body.replace(line, "", 1)
        self.assertNotIn("\n", body)
        draws = [d for d in body.split("\r") if d]
        self.assertGreater(len(draws), 3, repr(body[:300]))
        for draw in draws:
            self.assertRegex(draw, r"^[a-z]+ \d{1,3}%, \d+ (s|min \d\d s)"
                                   r"(, \d+(\.\d)? (B|KiB|MiB|GiB)/s)?(, ETA \d+ "
                                   r"(s|min \d\d s))?\x1b\[K$")
        self.assertRegex(draws[-1], last)
        percents = [int(re.match(r"^[a-z]+ (\d+)%", d).group(1)) for d in draws]
        self.assertTrue(any(0 < p < 100 for p in percents), percents)

    def test_on_a_terminal_import_validate_merge_and_render_lod_draw_one_line(self):
        target = work("progress-tty-prism")
        code, stdout, terminal = self.run_on_terminal(
            "import", os.path.join(ARGS.data, "PRISMelevation.tif"), target, "--patch-size", "65")
        self.assertEqual(code, 0, terminal)
        self.assertIn(b"imported", stdout)
        self.assert_one_updating_line(terminal, r"^import 100%")

        code, _, terminal = self.run_on_terminal("validate", target)
        self.assertEqual(code, 0, terminal)
        self.assert_one_updating_line(terminal, r"^validating 100%")

        detail = work("progress-tty-jack")
        self.assertEqual(vsm("import", os.path.join(ARGS.data, "jacksboro_fault_dem.tif"), detail,
                             "--patch-size", "65").returncode, 0)
        merged = work("progress-tty-merged")
        code, _, terminal = self.run_on_terminal("merge", target, detail, "--out", merged)
        self.assertEqual(code, 0, terminal)
        self.assert_one_updating_line(terminal, r"^publishing 100%")
        self.assertIn("placing", terminal)

        picture = os.path.join(ARGS.work, "progress-tty.png")
        code, _, terminal = self.run_on_terminal("render-lod", merged, picture, "--size", "256")
        self.assertEqual(code, 0, terminal)
        self.assert_one_updating_line(terminal, r"^drawing 100%")


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--work", required=True)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    shutil.rmtree(ARGS.work, ignore_errors=True)
    os.makedirs(ARGS.work)
    unittest.main(argv=[sys.argv[0], "-v", *rest])


if __name__ == "__main__":
    main()
