#!/usr/bin/env bash
# Benchmark (not a test): `vsm import` of a large raster against GDAL building the same overview
# levels of it.
#
# The input is SYNTHETIC: an 8193 x 8193 float32 GeoTIFF (EPSG:4326, 1 arc-second spacing, about
# 250 x 170 km in the Alps' latitudes) of fractal-ish terrain (value noise summed over octaves),
# generated here with numpy and GDAL's Python bindings. Quote it as synthetic.
#
# With 257 x 257 patches (vsm's default) the pyramid has 8192 / 256 = 32 = 2^5 patches per side
# at the bottom, so depth 5: five overview levels, the same as `gdaladdo -r average` with factors
# 2 4 8 16 32 (written as an external .ovr, -ro, on a copy of the file). They run one after the
# other on a warm page cache (the input was just written); gdaladdo uses one thread, vsm builds the
# four quarters of the pyramid on up to one thread per core. vsm also makes its output durable
# (its large files written with O_DIRECT, then one syncfs) before publishing it; gdaladdo does
# not. Each is run three times, alternating, on fresh output; the medians are compared.
#
#   tests/bench/import_bench.sh [path/to/vsm] [work-dir]
# Defaults: build/server/cli/vsm and a temporary directory (removed afterwards). Issue 17 asks
# for vsm import within 1.5x gdaladdo.
#
# VSM_BENCH_IMAGE_FACTOR=F (issue 28) adds an image F times finer than the DEM, also SYNTHETIC
# (RGB, per-pixel noise over smooth gradients, 8-bit, covering the DEM's quads exactly), which vsm
# drapes over the model (--texture: F texels per grid quad for F a power of two); gdaladdo then
# builds the same overview levels of the image too, and both times count. With VSM_BENCH_SIZE=2049
# and F=4 the image is 8192 x 8192. VSM_BENCH_IMPORT_OPTIONS adds options to vsm import (e.g.
# "--texels-per-quad 1", the layout before issue 28).
set -euo pipefail
source "$(dirname "$0")/bench_lib.sh"
SIZE=${VSM_BENCH_SIZE:-8193}
FACTOR=${VSM_BENCH_IMAGE_FACTOR:-0}
bench_vsm_and_work "$@"

echo "generating synthetic ${SIZE}x${SIZE} float32 terrain in $WORK ..."
"$PYTHON" - "$WORK/terrain.tif" "$SIZE" <<'EOF'
import sys
import numpy as np
from osgeo import gdal, osr

gdal.UseExceptions()
path, size = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(20240521)
z = np.zeros((size, size), dtype=np.float32)
amplitude = 1500.0
cells = 2
while cells <= 1024:
    # Value noise: a (cells+1)^2 lattice of random heights, bilinearly interpolated.
    lattice = rng.uniform(-1.0, 1.0, (cells + 1, cells + 1)).astype(np.float32)
    t = np.linspace(0.0, cells, size, dtype=np.float64)
    i = np.minimum(t.astype(np.int64), cells - 1)
    f = (t - i).astype(np.float32)
    rows = lattice[:, i] * (1 - f) + lattice[:, i + 1] * f          # (cells+1, size)
    z += amplitude * (rows[i, :] * (1 - f)[:, None] + rows[i + 1, :] * f[:, None])
    amplitude *= 0.5
    cells *= 2
z += 2000.0

ds = gdal.GetDriverByName("GTiff").Create(path, size, size, 1, gdal.GDT_Float32)
step = 1.0 / 3600.0
ds.SetGeoTransform((10.0, step, 0.0, 47.5, 0.0, -step))
srs = osr.SpatialReference()
srs.ImportFromEPSG(4326)
ds.SetProjection(srs.ExportToWkt())
band = ds.GetRasterBand(1)
band.SetNoDataValue(float("nan"))
band.WriteArray(z)
ds = None
EOF
ls -l "$WORK/terrain.tif"
read -r -a texture <<< "${VSM_BENCH_IMPORT_OPTIONS:-}"
if ((FACTOR > 0)); then
  echo "generating a synthetic RGB image $FACTOR times finer ..."
  "$PYTHON" - "$WORK/image.tif" "$SIZE" "$FACTOR" <<'EOF'
import sys
import numpy as np
from osgeo import gdal, osr

gdal.UseExceptions()
path, size, factor = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
side = (size - 1) * factor
step = 1.0 / 3600.0
ds = gdal.GetDriverByName("GTiff").Create(path, side, side, 3, gdal.GDT_Byte,
                                          ["TILED=YES", "INTERLEAVE=PIXEL"])
# From the first sample's centre to the last's: the DEM's quads, F x F pixels each.
ds.SetGeoTransform((10.0 + step / 2, step / factor, 0.0, 47.5 - step / 2, 0.0, -step / factor))
srs = osr.SpatialReference()
srs.ImportFromEPSG(4326)
ds.SetProjection(srs.ExportToWkt())
rng = np.random.default_rng(28)
x = np.arange(side)[None, :]
for top in range(0, side, 1024):
    rows = min(1024, side - top)
    y = np.arange(top, top + rows)[:, None]
    base = [x * 255 // side + 0 * y, y * 255 // side + 0 * x, (x + y) * 127 // side]
    for b in range(3):
        noise = rng.integers(-40, 41, size=(rows, side))
        ds.GetRasterBand(b + 1).WriteArray(np.clip(base[b] + noise, 0, 255).astype(np.uint8),
                                           0, top)
ds = None
EOF
  ls -l "$WORK/image.tif"
  texture+=(--texture "$WORK/image.tif")
fi
# Overview factors: one per level of vsm's pyramid (257 x 257 patches): 2 4 8 16 32 at 8193.
factors=()
for ((f = 2; f <= (SIZE - 1) / 256; f *= 2)); do factors+=("$f"); done

rm -rf "$WORK"/terrain-opc-*  # left by an interrupted run

# Three runs of each, alternating, each on fresh output: gdaladdo on a fresh copy of the input
# (no .ovr left from a run before: -ro would add to it), vsm into a new directory.
gdal_runs=()
vsm_runs=()
for run in 1 2 3; do
  rm -f "$WORK"/*-gdal.tif "$WORK"/*-gdal.tif.ovr
  cp "$WORK/terrain.tif" "$WORK/terrain-gdal.tif"
  if ((FACTOR > 0)); then cp "$WORK/image.tif" "$WORK/image-gdal.tif"; fi
  sync
  echo "run $run: gdaladdo -ro -r average terrain.tif ${factors[*]} (and the image) ..."
  start=$(now)
  gdaladdo -q -ro -r average "$WORK/terrain-gdal.tif" "${factors[@]}"
  if ((FACTOR > 0)); then gdaladdo -q -ro -r average "$WORK/image-gdal.tif" "${factors[@]}"; fi
  end=$(now)
  gdal_runs+=("$(echo "$end - $start" | bc -l)")

  # A new directory each run, all removed at the end: deleting the last run's 5,000 files just
  # before an import made ext4 without a journal (this bench's machine) skip each recently
  # deleted inode while allocating new ones (recently_deleted, 11 % of the import's profile), a
  # cost no user importing one model pays.
  sync
  echo "run $run: vsm import terrain.tif (patch size 257) ..."
  start=$(now)
  "$VSM" import "$WORK/terrain.tif" "$WORK/terrain-opc-$run" --patch-size 257 "${texture[@]}" \
    2>/dev/null
  end=$(now)
  vsm_runs+=("$(echo "$end - $start" | bc -l)")
done
gdal_seconds=$(median "${gdal_runs[@]}")
vsm_seconds=$(median "${vsm_runs[@]}")

printf 'input        synthetic %sx%s float32 GeoTIFF, %s\n' "$SIZE" "$SIZE" \
  "$(du -h "$WORK/terrain.tif" | cut -f1)"
if ((FACTOR > 0)); then
  printf 'image        synthetic %sx%s RGB, %s\n' "$(( (SIZE - 1) * FACTOR ))" \
    "$(( (SIZE - 1) * FACTOR ))" "$(du -h "$WORK/image.tif" | cut -f1)"
fi
printf 'gdaladdo     %8.2f s  median of %s s (overviews %s)\n' "$gdal_seconds" \
  "$(printf '%.2f ' "${gdal_runs[@]}" | sed 's/ $//')" \
  "$(du -ch "$WORK"/*-gdal.tif.ovr | tail -1 | cut -f1)"
printf 'vsm import   %8.2f s  median of %s s (OPC %s)\n' "$vsm_seconds" \
  "$(printf '%.2f ' "${vsm_runs[@]}" | sed 's/ $//')" "$(du -sh "$WORK/terrain-opc-1" | cut -f1)"
printf 'ratio        %8.2f  (vsm / gdaladdo; issue 17 asks for 1.5)\n' \
  "$(echo "$vsm_seconds / $gdal_seconds" | bc -l)"
rm -rf "$WORK"/terrain-opc-*
