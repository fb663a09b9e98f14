#!/usr/bin/env bash
# Re-projection throughput of planet-build against gdalwarp on the same
# inputs, in the same run (ISSUE #16, docs/BENCHMARKS.md).
#
# Inputs, made here with gdal-bin from the real SRTM tile in ../shared/data:
# the Rainier tile upsampled UP× (bilinear), then re-projected by gdalwarp to
# UTM zone 10 (EPSG:32610) and to polar stereographic (EPSG:3413) at RES
# metres, tiled GeoTIFFs. For each projected input:
#   1. planet-build builds a database from it (every output sample inverse-
#      mapped lat/lon -> projected CRS -> pixel, bilinear), elevation only;
#   2. gdalwarp -r bilinear -multi -wo NUM_THREADS=ALL_CPUS re-projects the
#      same input to EPSG:4326 with as many output samples as planet-build
#      stored.
# Both are timed with /usr/bin/time (wall, CPU, peak RSS); samples per
# second = output samples / wall seconds. Prints a table and a JSON line.
#
# Usage: scripts/bench-reproject.sh [UP=4] [RES=20] [WORK=/tmp/bench-reproject]
set -euo pipefail
cd "$(dirname "$0")/.."
UP="${1:-4}"
RES="${2:-20}"
WORK="${3:-/tmp/bench-reproject}"
SRC=../shared/data/mt_rainier_90m.tif
BIN=target/release/planet-build
for t in gdal_translate gdalwarp gdalinfo /usr/bin/time; do
  command -v "$t" >/dev/null || { echo "need $t (apt-get install gdal-bin time)" >&2; exit 1; }
done
[ -x "$BIN" ] || cargo build --release -p planet-preprocess
mkdir -p "$WORK"
N=$((1201 * UP))
CO=(-co TILED=YES -co BLOCKXSIZE=256 -co BLOCKYSIZE=256 -co BIGTIFF=IF_SAFER)
if [ ! -f "$WORK/up.tif" ]; then
  gdal_translate -q -r bilinear -outsize "$N" "$N" "${CO[@]}" "$SRC" "$WORK/up.tif"
fi
declare -A SRS=([utm]=EPSG:32610 [polar]=EPSG:3413)
rows=()
json="["
for name in utm polar; do
  in="$WORK/$name.tif"
  if [ ! -f "$in" ]; then
    gdalwarp -q -multi -wo NUM_THREADS=ALL_CPUS -r bilinear -t_srs "${SRS[$name]}" \
      -tr "$RES" "$RES" "${CO[@]}" "$WORK/up.tif" "$in"
  fi
  in_bytes=$(stat -c %s "$in")
  size=$(gdalinfo "$in" | sed -n 's/^Size is \([0-9]*\), \([0-9]*\)/\1x\2/p')
  # planet-build
  out=$(/usr/bin/time -f 'TIME %e %U %S %M' "$BIN" build --elevation "$in" \
    --vertical-datum ellipsoid --out "$WORK/$name.planetdb" --quiet 2>&1)
  pb_samples=$(echo "$out" | sed -n 's/.* \([0-9]*\) samples in .*/\1/p')
  read -r _ pb_wall pb_user pb_sys pb_rss <<<"$(echo "$out" | grep '^TIME')"
  rm -f "$WORK/$name.planetdb"
  # gdalwarp to the same number of output samples (a square-ish EPSG:4326
  # grid over the input's footprint: -ts W H with W*H = pb_samples).
  w=$(python3 -c "import math;print(int(math.sqrt($pb_samples)))")
  h=$(( pb_samples / w ))
  out=$(/usr/bin/time -f 'TIME %e %U %S %M' gdalwarp -q -overwrite -multi \
    -wo NUM_THREADS=ALL_CPUS -r bilinear -t_srs EPSG:4326 -ts "$w" "$h" \
    "$in" "$WORK/$name.warped.tif" 2>&1)
  read -r _ gw_wall gw_user gw_sys gw_rss <<<"$(echo "$out" | grep '^TIME')"
  gw_samples=$((w * h))
  rm -f "$WORK/$name.warped.tif"
  pb_rate=$(python3 -c "print(f'{$pb_samples/$pb_wall/1e6:.1f}')")
  gw_rate=$(python3 -c "print(f'{$gw_samples/$gw_wall/1e6:.1f}')")
  ratio=$(python3 -c "print(f'{($pb_samples/$pb_wall)/($gw_samples/$gw_wall):.2f}')")
  load=$(cut -d' ' -f1 /proc/loadavg)
  rows+=("| $name | $size, $((in_bytes / 1000000)) MB | planet-build | $pb_samples | ${pb_wall} s | $(python3 -c "print(f'{$pb_user+$pb_sys:.1f}')") s | **$pb_rate M/s** | $((pb_rss / 1024)) MB |")
  rows+=("| $name | | gdalwarp | $gw_samples | ${gw_wall} s | $(python3 -c "print(f'{$gw_user+$gw_sys:.1f}')") s | **$gw_rate M/s** | $((gw_rss / 1024)) MB |")
  rows+=("| $name | | ratio | | | | **${ratio}×** (load $load) | |")
  json+="{\"input\":\"$name\",\"input_bytes\":$in_bytes,\"planet_build\":{\"samples\":$pb_samples,\"wall_s\":$pb_wall,\"user_s\":$pb_user,\"sys_s\":$pb_sys,\"peak_rss_kib\":$pb_rss},\"gdalwarp\":{\"samples\":$gw_samples,\"wall_s\":$gw_wall,\"user_s\":$gw_user,\"sys_s\":$gw_sys,\"peak_rss_kib\":$gw_rss},\"ratio\":$ratio},"
done
echo "| input | size | tool | output samples | wall | CPU | samples/s | peak RSS |"
echo "|---|---|---|---|---|---|---|---|"
printf '%s\n' "${rows[@]}"
echo "${json%,}]"
