#!/usr/bin/python3
"""The viewer inside a tunnel (issue 33, item 7): a model in a local frame gets a free camera.

surfaces.py's horseshoe tunnel (240 degrees of a 3 m circle about the x axis, 16 m long, the floor
open: a local frame, z up, no georeference) is written as an organized PCD (its coarse scan A),
imported by the real `vsm import` and served by the real vsmd on 127.0.0.1:0 with the built viewer
(build.sh: the `viewer.site` fixture). Headless Chromium (browser_check.js, as viewer.browser) opens

    /viewer/?model=tunnel&eye=2,0,5.5&at=16,0,5.5&exaggeration=3

the camera inside the tunnel, 1.5 m above its axis, looking along it towards the far open end
(the exaggeration, heights above the WGS 84 ellipsoid, has no meaning in a local frame: the page
must undo it, or the pixels below would not match).

- The page: no console error, no failed request, nothing off 127.0.0.1, every tile loaded; it
  calls the frame `local`, its exaggeration is 1, and its near plane is half the model's finest
  resolution (GET /v1/models/tunnel) where the globe camera's would have been the model's
  radius / 1000.
- The pixels, against the tunnel's true surface: with the page's own camera matrices every
  pixel's ray is cast (numpy, no vsm code) against the surface surfaces.py defines (the cylinder
  displaced by A's undulation, iterated to the exact radius): it hits the wall where the wall
  exists (|angle from the top| <= 120 degrees, 0 <= x <= 16) and escapes elsewhere (the far open
  end, the open floor). Drawn (not the background colour) must match hit on at least
  MATCH_SHARE of the pixels clear of the panel, the legend and a BAND-pixel band along the
  expected outline; walls must be drawn on all four sides of the frame (the left, right and top
  edges almost wholly, the bottom edge at its right corner, its middle looking through the open
  floor), and the middle of the frame, the far open end, is background.
- The check can fail: the same screenshot against the tunnel turned by 90 degrees about its axis
  (the opening on a side) matches on far fewer pixels.
- The camera flies: with W held (a keydown on the window, as FlyControls listens) it moves
  forward along the tunnel until it is past x = 4 m, and after the keyup it has kept its line
  (y and z as the URL set them) and its direction. How far it went depends on the machine's
  speed; none of the checks do.

The screenshot (tunnel-inside.png) and its report are kept in --screenshots.

Run by ctest (viewer.tunnel):
    tunnel_viewer_test.py --vsmd build/server/vsmd --vsm build/server/cli/vsm
        --viewer build/viewer --web-tools build/web-tools --work build/.../tunnel-viewer
        --screenshots build/.../screenshots"""

import argparse
import math
import os
import shutil
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import browser_support  # noqa: E402
import harness  # noqa: E402
import surfaces  # noqa: E402
from browser_support import BACKGROUND, load_page, overlay_mask  # noqa: E402
from harness import Daemon  # noqa: E402

ARGS = None
MODEL = "tunnel"
PAGE_SECONDS = 90
EYE = (2.0, 0.0, 5.5)
AT = (16.0, 0.0, 5.5)
# The camera's x from window.vsmViewer.camera.view (column-major world -> camera): -(R^T t).x.
EYE_X = ("(() => { const m = window.vsmViewer.camera.view; "
         "return -(m[0] * m[12] + m[1] * m[13] + m[2] * m[14]); })()")
# Drawn must equal "the ray hits the wall" on this share of the pixels checked.
MATCH_SHARE = 0.97
# Pixels this close to the expected outline are not checked (antialiasing, the facets of A's
# 0.25 m grid, coarser levels far away).
BAND = 3
# A pixel is drawn when its colour differs from the background by more than this (sum of the
# channels' differences).
DRAWN = 24


def expected_hits(state, shape, turn=0.0):
    """(rows, cols) bool: whether each pixel's ray, from the page's camera, hits the tunnel's true
    surface (turned by `turn` radians about its axis, for the control)."""
    import numpy
    camera = state["camera"]

    def matrix(name):
        return numpy.array(camera[name], dtype=float).reshape(4, 4).T

    inverse = numpy.linalg.inv(matrix("projection") @ matrix("view") @ matrix("world"))
    rows, cols = shape[:2]
    y, x = numpy.mgrid[0:rows, 0:cols]
    ndc_x = (x + 0.5) / cols * 2 - 1
    ndc_y = 1 - (y + 0.5) / rows * 2

    def unproject(z):
        clip = numpy.stack([ndc_x, ndc_y, numpy.full_like(ndc_x, z), numpy.ones_like(ndc_x)],
                           axis=-1)
        world = clip @ inverse.T
        return world[..., :3] / world[..., 3:]

    origin = unproject(-1.0)
    direction = unproject(1.0) - origin
    direction /= numpy.linalg.norm(direction, axis=-1, keepdims=True)
    tunnel = surfaces.make("tunnel")
    # In the tunnel's cross-section (y, z - ZC): the ray leaves the cylinder of radius r at the
    # larger root (the eye is inside); r is the surface's radius there, R - f_A(u, v).
    oy, oz = origin[..., 1], origin[..., 2] - tunnel.ZC
    dy, dz = direction[..., 1], direction[..., 2]
    a = dy * dy + dz * dz
    b = 2 * (oy * dy + oz * dz)
    r = numpy.full(a.shape, tunnel.R)
    for _ in range(8):
        c = oy * oy + oz * oz - r * r
        t = (-b + numpy.sqrt(numpy.maximum(b * b - 4 * a * c, 0))) / numpy.maximum(2 * a, 1e-12)
        hit = origin + t[..., None] * direction
        u = hit[..., 0]
        phi = numpy.arctan2(hit[..., 1], hit[..., 2] - tunnel.ZC)
        r = tunnel.R - tunnel.f_a(u, tunnel.R * phi)
    phi = numpy.angle(numpy.exp(1j * (phi - turn)))
    return (a > 1e-12) & (u >= 0) & (u <= tunnel.a.u1) & (numpy.abs(phi) <= math.radians(120))


def band(mask, width):
    """Pixels within `width` of a change in `mask`."""
    import numpy
    near = numpy.zeros_like(mask)
    for dy in range(-width, width + 1):
        for dx in range(-width, width + 1):
            shifted = numpy.roll(numpy.roll(mask, dy, axis=0), dx, axis=1)
            near |= shifted != mask
    return near


class TunnelView(unittest.TestCase):
    daemon = None

    @classmethod
    def setUpClass(cls):
        os.makedirs(ARGS.screenshots, exist_ok=True)
        shutil.rmtree(ARGS.work, ignore_errors=True)
        surfaces.make("tunnel").write(ARGS.work)
        model = os.path.join(ARGS.work, MODEL)
        harness.vsm("import", os.path.join(ARGS.work, "A.pcd"), model, "--patch-size", "17",
                    "--texture", "none", check=True)

        def prepare(root):
            shutil.copytree(model, os.path.join(root, MODEL))

        cls.daemon = Daemon("--set", "threads.cpu=2", "--viewer-dir", ARGS.viewer,
                            "--log-level", "warn", prepare=prepare)

    @classmethod
    def tearDownClass(cls):
        if cls.daemon is not None:
            code = cls.daemon.stop()
            cls.daemon.cleanup(keep=code != 0)

    def test_a_camera_inside_the_tunnel_sees_its_walls_around_the_view(self):
        import numpy
        _, _, info = self.daemon.get_json("/v1/models/%s" % MODEL)
        page = "/viewer/?model=%s&eye=%s&at=%s&exaggeration=3" % (
            MODEL, ",".join(map(str, EYE)), ",".join(map(str, AT)))
        steps = [
            {"name": "forward", "run": "window.dispatchEvent(new KeyboardEvent('keydown', "
             "{code: 'KeyW'})); return true;"},
            {"name": "moved", "until": EYE_X + " > 4"},
            {"name": "stop", "run": "window.dispatchEvent(new KeyboardEvent('keyup', "
             "{code: 'KeyW'})); return true;"},
            {"name": "stopped", "until": "true"},
        ]
        report, pixels = load_page(self, self.daemon.base, page, "vsmViewer",
                                   "tunnel-inside", PAGE_SECONDS, steps)
        state = report["state"]
        self.assertEqual(report["consoleErrors"], [])
        self.assertEqual(state["failed"], 0, state["errors"])
        self.assertGreater(state["loaded"], 0)
        self.assertEqual(state["frame"], "local")
        self.assertEqual(state["exaggeration"], 1)
        finest = info["resolution"]["finest"]
        self.assertGreater(finest, 0)
        self.assertAlmostEqual(state["near"], finest / 2, delta=1e-6 * finest)
        # The camera is where the URL put it (the view matrix's inverse translation).
        view = numpy.array(state["camera"]["view"], dtype=float).reshape(4, 4).T
        self.assertLess(numpy.abs(numpy.linalg.inv(view)[:3, 3] - EYE).max(), 1e-3)

        drawn = numpy.abs(pixels.astype(int) - BACKGROUND).sum(axis=2) > DRAWN
        expected = expected_hits(state, pixels.shape)
        checked = ~overlay_mask(state, pixels.shape) & ~band(expected, BAND)
        match = float((drawn == expected)[checked].mean())
        turned = float((drawn == expected_hits(state, pixels.shape, math.pi / 2))[checked].mean())
        rows, cols = drawn.shape
        edge = 4

        def share(region):
            return float(drawn[region][checked[region]].mean())

        sides = {
            "left": share(numpy.s_[:, :edge]),
            "right": share(numpy.s_[:, cols - edge:]),
            "top": share(numpy.s_[:edge, :]),
            "bottom right corner": share(numpy.s_[rows - edge:, cols - 40:]),
            "bottom middle": share(numpy.s_[rows - edge:, cols // 2 - 20:cols // 2 + 20]),
            "middle": share(numpy.s_[rows // 2 - 20:rows // 2 + 20, cols // 2 - 20:cols // 2 + 20]),
        }
        numbers = {"pixels checked": int(checked.sum()), "match": round(match, 4),
                   "match turned 90 degrees": round(turned, 4), "drawn share by region": sides,
                   "near": state["near"], "finest": finest}
        print("tunnel: %s" % numbers, file=sys.stderr)
        self.assertGreaterEqual(match, MATCH_SHARE, numbers)
        self.assertLess(turned, match - 0.1, numbers)
        for side in ("left", "right", "top", "bottom right corner"):
            self.assertGreater(sides[side], 0.9, (side, numbers))
        for side in ("bottom middle", "middle"):
            self.assertLess(sides[side], 0.05, (side, numbers))

        done = {step["name"]: step for step in report["steps"]}
        self.assertIn("stopped", done, report["steps"])
        after = done["stopped"]["state"]
        self.assertEqual(report["consoleErrors"], [])
        self.assertEqual(after["failed"], 0, after["errors"])
        moved = numpy.array(after["camera"]["view"], dtype=float).reshape(4, 4).T
        position = numpy.linalg.inv(moved)[:3, 3]
        print("tunnel: after W, the camera at %s" % position.round(4).tolist(), file=sys.stderr)
        self.assertGreater(position[0], 4)
        self.assertLess(abs(position[1] - EYE[1]), 1e-3)
        self.assertLess(abs(position[2] - EYE[2]), 1e-3)
        # The same direction: the view's rotation unchanged.
        self.assertLess(numpy.abs(moved[:3, :3] - view[:3, :3]).max(), 1e-6)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--vsmd", required=True)
    parser.add_argument("--vsm", required=True)
    parser.add_argument("--viewer", required=True, help="the built viewer (build.sh)")
    parser.add_argument("--web-tools", required=True, help="prefix holding playwright-core")
    parser.add_argument("--work", required=True, help="where the tunnel is written and imported")
    parser.add_argument("--screenshots", required=True)
    parser.add_argument("--chromium", default=None)
    ARGS, rest = parser.parse_known_args()
    harness.configure(ARGS)
    browser_support.configure(ARGS)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
