"""The harness every integration test imports: the real vsmd on 127.0.0.1, port 0 (found through
--port-file), HTTP with the standard library only, the `vsm` command, synthetic rasters and the
small model readers the tests share. One copy of each; a test keeps only what is its own.

    import harness
    harness.configure(args)                  # --vsm, --vsmd, --proto of the test's command line
    daemon = harness.Daemon("--token", TOKEN, root=root)
    job = daemon.submit({"type": "merge", "target": "a", "source": "b"})
    job = daemon.wait_job(job["id"])
    daemon.stop()

Assertions are unittest's (tests/README.md says why): the helpers raise AssertionError, so a
failure inside one reads like a failed assert of the test that called it. The fault library's
hold and gate (hold.py) and the OPC readers that do not use our code (check_import.py,
merge_check.py, model_states.py) stay in their own files."""

import http.client
import json
import math
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
import unittest
import urllib.parse

import numpy as np

# The binaries and the proto directory, from configure(): a test's command line names them.
VSMD = None
VSM = None
PROTO = None
# How long a process may take to start (port file): a bound that only ends a hang, far above what
# a loaded machine or a sanitizer build needs.
START_DEADLINE = 120
# How long a job may take before a wait gives up: only ends a test that hangs.
JOB_DEADLINE = 600
FINAL_STATES = ("succeeded", "failed", "cancelled")
WGS84_PRJ = ('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
             'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]')


def configure(args):
    """Takes --vsmd, --vsm and --proto from a parsed command line (those it has)."""
    global VSMD, VSM, PROTO
    VSMD = getattr(args, "vsmd", None) or VSMD
    VSM = getattr(args, "vsm", None) or VSM
    PROTO = getattr(args, "proto", None) or PROTO


def run_tests(argv, skip_code=None):
    """unittest's main over the script's cases (`argv`: what the script's parser left):
    exits 1 on a failure; `skip_code` (ctest's SKIP_RETURN_CODE) when every case was skipped."""
    result = unittest.main(module="__main__", argv=[sys.argv[0], *argv], verbosity=2,
                           exit=False).result
    if not result.wasSuccessful():
        sys.exit(1)
    if skip_code is not None and result.testsRun and len(result.skipped) == result.testsRun:
        sys.exit(skip_code)
    sys.exit(0)


def check(test, condition, message):
    """One step of a scenario test: printed as it comes ("ok" or "FAIL"), failed as a subtest of
    `test`, so the steps after it still run and every failed one is listed."""
    print(("ok   " if condition else "FAIL ") + message, flush=True)
    with test.subTest(message):
        test.assertTrue(condition, message)


# ---- the daemon ---------------------------------------------------------------------------------

class Daemon:
    """One vsmd process on 127.0.0.1:0 over a data root; the port comes from --port-file. The
    token of a `--token` flag is sent by the JSON helpers (json, submit)."""

    def __init__(self, *flags, config=None, prepare=None, root=None, env=None, vsmd=None,
                 port_file=None, log_path=None, preexec_fn=None, start_deadline=START_DEADLINE,
                 token=None):
        """`prepare(dir)` fills the data root before the daemon starts; `root` reuses one (else a
        temporary directory); `env` is the process's environment (default: this one's); the port
        file and the log are in the data root unless named; `config` (a dict) is written beside
        them and passed with --config; `token` is the one the JSON helpers send (default: the
        --token flag's)."""
        self.dir = root or tempfile.mkdtemp(prefix="vsmd-test-")
        if prepare is not None:
            prepare(self.dir)
        self.port_file = port_file or os.path.join(self.dir, "port")
        self.log_path = log_path or os.path.join(self.dir, "vsmd.log")
        if os.path.exists(self.port_file):
            os.remove(self.port_file)
        if token is None and "--token" in flags:
            token = flags[flags.index("--token") + 1]
        self.token = token
        args = [vsmd or VSMD, "--listen", "127.0.0.1:0", "--data-root", self.dir,
                "--port-file", self.port_file, *flags]
        if config is not None:
            path = os.path.join(self.dir, "vsmd.json")
            with open(path, "w") as f:
                json.dump(config, f)
            args += ["--config", path]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log,
                                         stderr=subprocess.STDOUT, env=env, preexec_fn=preexec_fn)
        deadline = time.monotonic() + start_deadline
        while not os.path.exists(self.port_file):
            if self.proc.poll() is not None:
                raise AssertionError("vsmd exited with %d:\n%s"
                                     % (self.proc.returncode, self.log()))
            if time.monotonic() > deadline:
                self.kill()
                raise AssertionError("vsmd wrote no port file within %d s:\n" % start_deadline
                                     + self.log())
            time.sleep(0.02)
        with open(self.port_file) as f:
            self.port = int(f.read())
        self.base = "http://127.0.0.1:%d" % self.port

    @property
    def pid(self):
        return self.proc.pid

    def log(self):
        with open(self.log_path, errors="replace") as f:
            return f.read()

    def connection(self, timeout=10):
        return http.client.HTTPConnection("127.0.0.1", self.port, timeout=timeout)

    def socket(self, timeout=10):
        return socket.create_connection(("127.0.0.1", self.port), timeout=timeout)

    def request(self, method, path, body=None, headers=None, timeout=10):
        """One request on a fresh connection: (status, headers, body bytes)."""
        conn = self.connection(timeout)
        try:
            conn.request(method, path, body=body, headers=headers or {})
            response = conn.getresponse()
            return response.status, response.headers, response.read()
        finally:
            conn.close()

    def get_json(self, path, timeout=10):
        """GET `path`: (status, headers, the body parsed)."""
        status, headers, body = self.request("GET", path, timeout=timeout)
        return status, headers, json.loads(body)

    def json(self, method, path, body=None, timeout=60):
        """A request with a JSON body (or none) and the daemon's token: (status, headers, the
        answer parsed, None when empty)."""
        status, headers, data = request(self.base + path, method, body, timeout=timeout,
                                     token=self.token)
        return status, headers, json.loads(data) if data else None

    def submit(self, body, path="/v1/jobs", status=202):
        """POSTs a job (or a model: path="/v1/models") and returns the job's answer; the status
        must be `status`."""
        code, _, job = self.json("POST", path, body)
        if code != status:
            raise AssertionError("POST %s %r: %d %r" % (path, body, code, job))
        return job

    def wait_job(self, job_id, timeout=JOB_DEADLINE, until=None, seen=None, interval=0.02):
        """Polls a job until `until(job)` (default: a final state) and returns it; `seen`
        collects (state, stage, progress) along the way."""
        deadline = time.monotonic() + timeout
        while True:
            status, _, job = self.get_json("/v1/jobs/" + job_id)
            if status != 200:
                raise AssertionError("GET /v1/jobs/%s: %d %r" % (job_id, status, job))
            if seen is not None:
                seen.append((job["state"], job["stage"], job["progress"]))
            if until(job) if until else job["state"] in FINAL_STATES:
                return job
            if time.monotonic() > deadline:
                raise AssertionError("job %s not done after %d s: %r" % (job_id, timeout, job))
            time.sleep(interval)

    def import_model(self, model_id, raster, patch_size, timeout=300):
        """Imports `raster` (a path in the data root) as `model_id` through the jobs API and waits
        for the job, which must succeed."""
        job = self.submit({"id": model_id, "source": {"import": raster, "patch_size": patch_size}},
                          path="/v1/models")
        job = self.wait_job(job["id"], timeout=timeout)
        if job["state"] != "succeeded":
            raise AssertionError("import of %s: %r" % (raster, job))
        return job

    def keys(self, model, rev=None):
        """Every patch key of a model's hierarchy (of revision `rev`), depth first."""
        path = "/v1/models/%s/hierarchy" % model + ("" if rev is None else "?rev=%d" % rev)
        status, _, tree = self.get_json(path)
        if status != 200:
            raise AssertionError("GET %s: %d %r" % (path, status, tree))
        return keys(tree)

    def stop(self, timeout=20):
        """SIGTERM and the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError("vsmd did not exit within %d s of SIGTERM:\n%s"
                                 % (timeout, self.log()))

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def cleanup(self, keep=False):
        self.kill()
        if not keep:
            shutil.rmtree(self.dir, ignore_errors=True)


# ---- HTTP -------------------------------------------------------------------------------------

def request(url, method="GET", body=None, timeout=30, token=None, headers=None):
    """One request to a URL on a fresh connection: (status, headers, body bytes). A dict or list
    body is sent as JSON; a token as a bearer; no redirect is followed, no proxy used."""
    parts = urllib.parse.urlsplit(url)
    headers = dict(headers or {})
    if body is not None and not isinstance(body, (bytes, str)):
        body = json.dumps(body).encode()
        headers.setdefault("Content-Type", "application/json")
    if token:
        headers["Authorization"] = "Bearer " + token
    conn = http.client.HTTPConnection(parts.hostname, parts.port or 80, timeout=timeout)
    try:
        conn.request(method, parts.path + ("?" + parts.query if parts.query else ""), body=body,
                     headers=headers)
        response = conn.getresponse()
        return response.status, response.headers, response.read()
    finally:
        conn.close()


def read_until_closed(sock, limit=1 << 20):
    chunks = []
    while sum(map(len, chunks)) < limit:
        try:
            data = sock.recv(65536)
        except ConnectionResetError:
            break
        if not data:
            break
        chunks.append(data)
    return b"".join(chunks)


def read_response(sock):
    """Reads one response with a Content-Length (or none) from a raw socket: (status, headers
    text, body)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            raise AssertionError("connection closed before a response: %r" % data)
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    head = head.decode("latin-1")
    match = re.search(r"(?im)^content-length:\s*(\d+)", head)
    length = int(match.group(1)) if match else 0
    while len(body) < length:
        chunk = sock.recv(65536)
        if not chunk:
            break
        body += chunk
    return int(head.split(" ")[1]), head, body


def example(name):
    """proto/examples/<name>, parsed."""
    with open(os.path.join(PROTO, "examples", name)) as f:
        return json.load(f)


def shape(value, maps=("resident_bytes_by_model",), key=None):
    """The structure of a JSON value: dict keys and value kinds, recursively. Objects named in
    `maps` are maps (any keys, possibly none) of numbers."""
    if isinstance(value, dict):
        if key in maps:
            if any(shape(v) != "number" for v in value.values()):
                return "map with other values than numbers"
            return "map of numbers"
        return {k: shape(v, maps, k) for k, v in value.items()}
    if isinstance(value, list):
        return "list"
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, (int, float)):
        return "number"
    return type(value).__name__


def metric(text, name, labels=""):
    """The value of one sample of the Prometheus text, e.g. metric(t, "x", '{a="b"}')."""
    match = re.search(r"(?m)^%s%s (\S+)$" % (re.escape(name), re.escape(labels)), text)
    assert match, "no sample %s%s" % (name, labels)
    return float(match.group(1))


def rss(pid):
    """A process's resident memory in bytes (/proc)."""
    with open("/proc/%d/status" % pid) as f:
        return int(re.search(r"(?m)^VmRSS:\s+(\d+) kB", f.read()).group(1)) * 1024


# ---- models -----------------------------------------------------------------------------------

def walk(node):
    """A hierarchy answer's nodes (from its "root"), depth first."""
    yield node
    for child in node.get("children", []):
        yield from walk(child)


def keys(tree):
    """The patch keys of a hierarchy answer, depth first."""
    return [node["key"] for node in walk(tree["root"])]


def decode_aara(data):
    """(type name, sizes, payload) of .aara bytes, per ../shared/docs/OPC.md."""
    n = data[0]
    name = data[1:1 + n].decode("ascii")
    dims = data[1 + n]
    sizes = struct.unpack_from("<%di" % dims, data, 2 + n)
    return name, sizes, data[2 + n + 4 * dims:]


# The element types of .aara arrays of 2-D grids (OPC.md): numpy type and components.
AARA_TYPES = {"V2f": ("<f4", 2), "V2d": ("<f8", 2), "V3f": ("<f4", 3), "V3d": ("<f8", 3)}


def read_aara(path):
    """(type name, [columns, rows], values of shape (rows, columns, components) in the file's
    type) of an .aara file holding a grid of vectors; its length must fit its header."""
    import numpy as np
    with open(path, "rb") as f:
        data = f.read()
    name, sizes, payload = decode_aara(data)
    if name not in AARA_TYPES or len(sizes) != 2:
        raise ValueError("%s: unexpected array %s with %d dimensions" % (path, name, len(sizes)))
    dtype, components = AARA_TYPES[name]
    if len(payload) != sizes[0] * sizes[1] * components * np.dtype(dtype).itemsize:
        raise ValueError("%s: %d bytes do not hold %s %s" % (path, len(data), name, list(sizes)))
    values = np.frombuffer(payload, dtype=dtype).reshape(sizes[1], sizes[0], components)
    return name, list(sizes), values


# ---- the vsm command and its inputs --------------------------------------------------------------

def vsm(*args, check=False, timeout=600, env=None):
    """`vsm args...` with its output captured as text; raises with the output on failure when
    `check`."""
    result = subprocess.run([VSM, *map(str, args)], capture_output=True, text=True,
                            timeout=timeout, env=env)
    if check and result.returncode != 0:
        raise AssertionError("vsm %s exited %d:\n%s%s" % (" ".join(map(str, args)),
                                                         result.returncode, result.stdout,
                                                         result.stderr))
    return result


def import_dem(raster, out, patch_size, *options, timeout=600):
    """`vsm import raster out --patch-size N options...`, which must succeed."""
    return vsm("import", raster, out, "--patch-size", patch_size, *options, check=True,
               timeout=timeout)


def write_dem(path, size, cell=0.0005, west=10.0, south=45.0, slope=0.5):
    """A synthetic DEM of size x size samples (smooth hills rising `slope` m a row, metres) as an
    ESRI ASCII grid with a WGS 84 .prj beside it: a raster GDAL reads, written with the standard
    library only."""
    with open(path, "w") as f:
        f.write("ncols %d\nnrows %d\nxllcorner %r\nyllcorner %r\ncellsize %r\n"
                % (size, size, west, south, cell))
        for row in range(size):
            f.write(" ".join("%.2f" % (500 + 40 * math.sin(col / 9.0) * math.cos(row / 13.0)
                                       + slope * row) for col in range(size)))
            f.write("\n")
    with open(os.path.splitext(path)[0] + ".prj", "w") as f:
        f.write(WGS84_PRJ)


def band_heights(band):
    """A GDAL band's heights as float64 rows x cols with its scale and offset applied, NaN where
    undefined: not finite, or its no-data value (as float32 when the band is)."""
    import numpy as np
    from osgeo import gdal
    values = band.ReadAsArray().astype(np.float64)
    nodata = band.GetNoDataValue()
    undefined = ~np.isfinite(values)
    if nodata is not None:
        if band.DataType == gdal.GDT_Float32:
            nodata = float(np.float32(nodata))
        undefined |= values == nodata
    return np.where(undefined, np.nan,
                    values * (band.GetScale() or 1.0) + (band.GetOffset() or 0.0))


def read_raster(path):
    """(heights as band_heights gives them, geotransform) of a DEM's first band, by GDAL."""
    from osgeo import gdal
    gdal.UseExceptions()
    dataset = gdal.Open(path)
    return band_heights(dataset.GetRasterBand(1)), dataset.GetGeoTransform()


def bilinear(image, x, y):
    """image (bands, rows, cols) at pixel-edge coordinates (x, y), numbers or arrays of one shape:
    bilinear between centres, the edge pixels beyond them."""
    cx, cy = np.asarray(x, dtype=float) - 0.5, np.asarray(y, dtype=float) - 0.5
    x0, y0 = np.floor(cx).astype(int), np.floor(cy).astype(int)
    fx, fy = cx - x0, cy - y0
    rows, cols = image.shape[1], image.shape[2]

    def px(i, j):
        return image[:, np.clip(j, 0, rows - 1), np.clip(i, 0, cols - 1)].astype(float)

    return ((1 - fy) * ((1 - fx) * px(x0, y0) + fx * px(x0 + 1, y0))
            + fy * ((1 - fx) * px(x0, y0 + 1) + fx * px(x0 + 1, y0 + 1)))


def write_raster(path, heights, west, north, pixel, nodata=None, epsg=4326):
    """A float32 GeoTIFF of a 2-D array (row 0 north), square pixels of `pixel` degrees from
    (west, north), in the CRS of `epsg` (WGS 84; None: no CRS)."""
    import numpy as np
    from osgeo import gdal, osr
    gdal.UseExceptions()
    rows, cols = heights.shape
    ds = gdal.GetDriverByName("GTiff").Create(path, cols, rows, 1, gdal.GDT_Float32)
    ds.SetGeoTransform((west, pixel, 0.0, north, 0.0, -pixel))
    if epsg is not None:
        srs = osr.SpatialReference()
        srs.ImportFromEPSG(epsg)
        ds.SetProjection(srs.ExportToWkt())
    band = ds.GetRasterBand(1)
    if nodata is not None:
        band.SetNoDataValue(nodata)
    band.WriteArray(heights.astype(np.float32))
    ds.FlushCache()
    ds = None


def fault_env(lib, prefix, base=None, **variables):
    """The environment of a process run under the fault library (tests/fault): LD_PRELOAD, the
    path prefix it acts on, and VSM_FAULT_<NAME> for each keyword (None leaves one out)."""
    env = dict(os.environ if base is None else base)
    env["LD_PRELOAD"] = lib
    env["VSM_FAULT_PREFIX"] = prefix
    # Under ASan the runtime must come first; the library only forwards calls.
    env["ASAN_OPTIONS"] = (env.get("ASAN_OPTIONS", "") + ":verify_asan_link_order=0").lstrip(":")
    for name, value in variables.items():
        if value is not None:
            env["VSM_FAULT_" + name.upper()] = str(value)
    return env
