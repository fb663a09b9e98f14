#!/usr/bin/env bash
# Bytes per sample of the record codecs (docs/BENCHMARKS.md "Bytes per
# sample"): builds each database with the legacy codecs and the format v2
# ones (elevation ids 1, 2 and 3), prints a table of bytes per sample from
# `planet-build inspect --json`
# and the error against the source from `planet-build verify --json` with the
# build's source options.
#
#   scripts/bytes-per-sample.sh [OUT_DIR] [real|default|deep]...
#
# Needs target/release/planet-build (cargo build --release -p
# planet-preprocess) and, for `real`, ../shared/data.
set -euo pipefail
cd "$(dirname "$0")/.."
B=target/release/planet-build
OUT=${1:-/tmp/bps}
shift || true
SETS=${*:-real default deep}
mkdir -p "$OUT"
D=../shared/data
declare -A SRC=(
  [real]="--elevation $D/earth_etopo5_30arcmin.tif $D/mt_rainier_90m.tif $D/mt_everest_90m.tif --colour $D/earth_bluemarble_2048x1024.tif"
  [default]="--procedural --seed 1 --levels 4"
  [deep]="--procedural --seed 1 --levels 6 --detail 46.85,-121.76,60,14 --detail 27.95,86.93,60,14"
)
declare -A VARIANT=(
  [legacy]="--elevation-codec legacy --colour-quality lossless-legacy"
  [id1]="--elevation-codec quantised-1"
  [lossless]="--colour-quality lossless"
  [default]=""
  [1m-id1]="--elevation-codec quantised-1 --max-error 1"
  [1m-id2]="--elevation-codec quantised-2 --max-error 1"
  [1m]="--max-error 1"
)
for s in $SETS; do
  variants="legacy id1 lossless default 1m-id1 1m-id2 1m"
  [ "$s" = deep ] && variants="legacy default 1m-id2 1m"
  for v in $variants; do
    db="$OUT/$s-$v.planetdb"
    echo "# $B build ${SRC[$s]} ${VARIANT[$v]} --quiet --out $db" >&2
    # shellcheck disable=SC2086
    $B build ${SRC[$s]} ${VARIANT[$v]} --quiet --out "$db" > "$OUT/$s-$v.build.txt"
    $B inspect --json "$db" > "$OUT/$s-$v.inspect.json"
    # Verify against the source: the deep planet only for its 1 m database
    # (it regenerates every leaf).
    if [ "$s" != deep ] || [ "$v" = 1m ]; then
      # shellcheck disable=SC2086
      $B verify "$db" ${SRC[$s]} --json > "$OUT/$s-$v.verify.json"
    fi
  done
done
python3 - "$OUT" $SETS <<'PY'
import json, os, re, sys
out, sets = sys.argv[1], sys.argv[2:]
def load(p):
    return json.load(open(p)) if os.path.exists(p) else None
print("| data | codecs | elevation B/sample | × legacy | colour B/texel | × legacy | colour PSNR dB (lowest record) | max elevation error m | build M samples/s |")
print("|---|---|---|---|---|---|---|---|---|")
for s in sets:
    leg = load(f"{out}/{s}-legacy.inspect.json")
    for v in ["legacy", "id1", "lossless", "default", "1m-id1", "1m-id2", "1m"]:
        r = load(f"{out}/{s}-{v}.inspect.json")
        if r is None:
            continue
        e, c = r["elevation"], r["colour"]
        eb, cb = e["bytes"] / e["samples"], c["bytes"] / c["samples"]
        le = leg["elevation"]["bytes"] / leg["elevation"]["samples"]
        lc = leg["colour"]["bytes"] / leg["colour"]["samples"]
        ver = load(f"{out}/{s}-{v}.verify.json")
        psnr = err = "–"
        if ver:
            p, m = ver.get("colour_psnr"), ver.get("colour_min_record_psnr")
            psnr = "exact" if p is None or p > 1e300 else f"{p:.2f} ({m:.2f})"
            err = f"{ver['elevation_max_error_m']:g} (bound {ver['elevation_bound_m']:g})"
        b = open(f"{out}/{s}-{v}.build.txt").read()
        rate = re.search(r"\(([\d.]+) M samples/s\)", b)
        names = f"{e['codec']} {e['codec_params'].get('max_error_m', '')} / {c['codec']} {c['codec_params'].get('target_psnr', '')}"
        print(f"| {s} | {v}: {names.strip()} | {eb:.4f} | {eb/le:.3f} | {cb:.4f} | {cb/lc:.3f} | {psnr} | {err} | {rate.group(1) if rate else '?'} |")
PY
