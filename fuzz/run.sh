#!/usr/bin/env bash
# Short fuzzing run of every target (CI), or a longer one:
#   fuzz/run.sh            # 15 s per target
#   FUZZ_SECONDS=3600 fuzz/run.sh   # an hour per target
# Needs cargo-fuzz (installed if missing). Runs on stable Rust without a
# sanitizer (--sanitizer none): libFuzzer's coverage guidance and Rust's own
# bounds and overflow checks (debug assertions on) find the panics we care
# about. Any crash is saved under fuzz/artifacts/TARGET/ and makes this fail;
# copy it into fuzz/regressions/TARGET/ (and fix the bug):
# `cargo test -p planet-server --test fuzz_regressions` replays every file of
# fuzz/regressions/TARGET/ and fuzz/corpus/TARGET/ without cargo-fuzz.
# Targets: protocol_frames, db_record, db_header (planet-core/-protocol),
# control_session (the server's control-stream state machine, stateful),
# db_open_request (a database file opened as the server opens it, with the
# requests a client sends for it checked as the server checks them),
# server_config (planet-server's TOML parsing and validation) and
# raster_readers (planet-preprocess: GeoTIFF/GeoKeys/CRS readers on untrusted
# bytes).
set -euo pipefail
cd "$(dirname "$0")"
secs="${FUZZ_SECONDS:-15}"
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
for t in $(cargo fuzz list); do
  mkdir -p "corpus/$t"
  echo "fuzz: $t for ${secs}s"
  dict=(); [ -f "dicts/$t.dict" ] && dict=(-dict="dicts/$t.dict")
  cargo fuzz run --sanitizer none -O -a "$t" "corpus/$t" -- \
    -max_total_time="$secs" -max_len=40000 -print_final_stats=1 "${dict[@]}" 2>&1 \
    | grep -E "^(Done|stat::number_of_executed_units)|panicked|SUMMARY|crash" || true
  if ls "artifacts/$t"/crash-* >/dev/null 2>&1; then
    echo "fuzz: $t found a crash: $(ls artifacts/$t/crash-*)"; exit 1
  fi
done
