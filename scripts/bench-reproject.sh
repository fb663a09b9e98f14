#!/usr/bin/env bash
# Re-projection throughput of planet-build against gdalwarp on the same
# inputs, in the same run (ISSUE #16, docs/BENCHMARKS.md).
#
# Inputs, made here with gdal-bin from the real SRTM tile in ../shared/data:
# the Rainier tile upsampled UP× (gdal_translate, bilinear), then re-projected
# by gdalwarp to UTM zone 10 (EPSG:32610) and to polar stereographic
# (EPSG:3413), tiled GeoTIFFs whose resolution is chosen so that each is
# about MB megabytes (a 300 m warp measures the footprint first). For each
# projected input:
#   1. planet-build build: a database from it (every output sample
#      inverse-mapped lat/lon -> projected CRS -> pixel, bilinear, voids
#      filled, LODs, encoding, file), elevation only, leaves at MAX_LEVEL;
#   2. planet-build resample: the same leaf grids re-projected and sampled,
#      nothing else (the re-projection part alone);
#   3. gdalwarp -r bilinear -multi -wo NUM_THREADS=ALL_CPUS re-projects the
#      same input to EPSG:4326 with as many output samples as planet-build
#      stored.
# Each is timed with /usr/bin/time (wall, CPU, peak RSS); samples per
# second = output samples / wall seconds, and per CPU-second = output
# samples / (user + sys). Prints a table and a JSON line.
#
# Usage: scripts/bench-reproject.sh [UP=4] [MB=1100] [MAX_LEVEL=15] [WORK=/tmp/bench-reproject]
# (PLANET_BUILD=path picks the binary; default target/release/planet-build.)
set -euo pipefail
cd "$(dirname "$0")/.."
UP="${1:-4}"
MB="${2:-1100}"
MAX_LEVEL="${3:-15}"
WORK="${4:-/tmp/bench-reproject}"
SRC=../shared/data/mt_rainier_90m.tif
BIN="${PLANET_BUILD:-target/release/planet-build}"
for t in gdal_translate gdalwarp gdalinfo python3 /usr/bin/time; do
  command -v "$t" >/dev/null || { echo "need $t (apt-get install gdal-bin python3 time)" >&2; exit 1; }
done
[ -x "$BIN" ] || cargo build --release -p planet-preprocess
mkdir -p "$WORK"
N=$((1201 * UP))
CO=(-of GTiff -co TILED=YES -co BLOCKXSIZE=256 -co BLOCKYSIZE=256 -co BIGTIFF=IF_SAFER)
if [ ! -f "$WORK/up.tif" ]; then
  gdal_translate -q -r bilinear -outsize "$N" "$N" "${CO[@]}" "$SRC" "$WORK/up.tif"
fi
py() { python3 -c "$1"; }
size_of() { gdalinfo "$1" | sed -n 's/^Size is \([0-9]*\), \([0-9]*\)/\1 \2/p'; }
declare -A SRS=([utm]=EPSG:32610 [polar]=EPSG:3413)
rows=()
json="["
for name in utm polar; do
  in="$WORK/$name-${MB}MB.tif"
  if [ ! -f "$in" ]; then
    gdalwarp -q -overwrite -t_srs "${SRS[$name]}" -tr 300 300 "$SRC" "$WORK/$name-300m.tif"
    read -r w h <<<"$(size_of "$WORK/$name-300m.tif")"
    res=$(py "import math;print(f'{300*math.sqrt($w*$h*2/($MB*1e6)):.3f}')")
    gdalwarp -q -multi -wo NUM_THREADS=ALL_CPUS -r bilinear -t_srs "${SRS[$name]}" \
      -tr "$res" "$res" "${CO[@]}" "$WORK/up.tif" "$in.part"
    mv "$in.part" "$in"
  fi
  in_bytes=$(stat -c %s "$in")
  read -r w h <<<"$(size_of "$in")"
  # planet-build build
  out=$(/usr/bin/time -f 'TIME %e %U %S %M' "$BIN" build --elevation "$in" \
    --vertical-datum ellipsoid --max-level "$MAX_LEVEL" --out "$WORK/$name.planetdb" --quiet 2>&1)
  pb_samples=$(echo "$out" | sed -n 's/.* \([0-9]*\) samples in .*/\1/p')
  read -r _ pb_wall pb_user pb_sys pb_rss <<<"$(echo "$out" | grep '^TIME')"
  rm -f "$WORK/$name.planetdb"
  # planet-build resample (re-projection and sampling alone)
  out=$(/usr/bin/time -f 'TIME %e %U %S %M' "$BIN" resample --elevation "$in" \
    --vertical-datum ellipsoid --max-level "$MAX_LEVEL" 2>&1)
  rs_samples=$(echo "$out" | sed -n 's/.* \([0-9]*\) samples in .*/\1/p')
  read -r _ rs_wall rs_user rs_sys rs_rss <<<"$(echo "$out" | grep '^TIME')"
  # gdalwarp to the same number of output samples (a square-ish EPSG:4326
  # grid over the input's footprint: -ts W H with W*H = pb_samples).
  gw=$(py "import math;print(int(math.sqrt($pb_samples)))")
  gh=$((pb_samples / gw))
  out=$(/usr/bin/time -f 'TIME %e %U %S %M' gdalwarp -q -overwrite -multi \
    -wo NUM_THREADS=ALL_CPUS -r bilinear -t_srs EPSG:4326 -ts "$gw" "$gh" \
    -co BIGTIFF=YES "$in" "$WORK/$name.warped.tif" 2>&1)
  read -r _ gw_wall gw_user gw_sys gw_rss <<<"$(echo "$out" | grep '^TIME')"
  gw_samples=$((gw * gh))
  rm -f "$WORK/$name.warped.tif"
  load=$(cut -d' ' -f1 /proc/loadavg)
  row() { # tool samples wall user sys rss
    py "s,wl,u,sy,r=$2,$3,$4,$5,$6
print(f'| $name | ${w}×${h}, {$in_bytes/1e6:.0f} MB | $1 | {s/1e6:.1f} M | {wl} s | {u+sy:.1f} s | **{s/wl/1e6:.1f} M** | **{s/(u+sy)/1e6:.1f} M** | {r/1024:.0f} MB |')"
  }
  rows+=("$(row "planet-build build" "$pb_samples" "$pb_wall" "$pb_user" "$pb_sys" "$pb_rss")")
  rows+=("$(row "planet-build resample" "$rs_samples" "$rs_wall" "$rs_user" "$rs_sys" "$rs_rss")")
  rows+=("$(row gdalwarp "$gw_samples" "$gw_wall" "$gw_user" "$gw_sys" "$gw_rss")")
  ratio=$(py "print(f'{($pb_samples/$pb_wall)/($gw_samples/$gw_wall):.2f}')")
  ratio_cpu=$(py "print(f'{($pb_samples/($pb_user+$pb_sys))/($gw_samples/($gw_user+$gw_sys)):.2f}')")
  rows+=("| $name | | build ÷ gdalwarp | | | | **${ratio}×** | **${ratio_cpu}×** | (load $load) |")
  json+="{\"input\":\"$name\",\"input_bytes\":$in_bytes,\"max_level\":$MAX_LEVEL,\"planet_build\":{\"samples\":$pb_samples,\"wall_s\":$pb_wall,\"user_s\":$pb_user,\"sys_s\":$pb_sys,\"peak_rss_kib\":$pb_rss},\"resample\":{\"samples\":$rs_samples,\"wall_s\":$rs_wall,\"user_s\":$rs_user,\"sys_s\":$rs_sys,\"peak_rss_kib\":$rs_rss},\"gdalwarp\":{\"samples\":$gw_samples,\"wall_s\":$gw_wall,\"user_s\":$gw_user,\"sys_s\":$gw_sys,\"peak_rss_kib\":$gw_rss},\"ratio_wall\":$ratio,\"ratio_cpu\":$ratio_cpu},"
done
echo "| input | size | tool | output samples | wall | CPU | samples/s (wall) | samples/CPU-s | peak RSS |"
echo "|---|---|---|---|---|---|---|---|---|"
printf '%s\n' "${rows[@]}"
echo "${json%,}]"
