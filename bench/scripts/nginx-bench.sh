#!/usr/bin/env bash
# planet-server (QUIC) against Debian's nginx (HTTPS byte ranges) on the same
# database file, same request list; then the 1000-client load test.
#
#   bench/scripts/nginx-bench.sh [DB] [-- extra planet-bench server args]
#
# DB defaults to the default procedural planet (built to /tmp on first use).
# planet-bench starts nginx itself (/usr/sbin/nginx -p TMP -e TMP/error.log
# -c TMP/nginx.conf: TLS 1.3 with a fresh self-signed certificate, sendfile,
# keep-alive, HTTP/1.1 and HTTP/2, 127.0.0.1 only) and stops it at the end;
# the generated configuration is the one in bench/src/server_bench.rs
# (Nginx::start). The closed-loop run (throughput) is followed by an
# open-loop run at RATES (default 1000,2000,3000 requests/s over the 200
# clients, Poisson arrivals, latency from the scheduled send time); set
# RATES= to skip it. Set LOAD=0 to skip the load test.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$ROOT"
DB_ARGS=()
if [ $# -gt 0 ] && [ "$1" != "--" ]; then
  DB_ARGS=(--db "$1")
  shift
fi
[ "${1:-}" = "--" ] && shift
if ! command -v "${NGINX:-/usr/sbin/nginx}" >/dev/null 2>&1; then
  echo "nginx not found: apt-get install nginx (or set NGINX)" >&2
  exit 2
fi
cargo build --release -p planet-bench -p planet-server-bin
echo "== $(date -u +%FT%TZ) uptime: $(uptime)"
target/release/planet-bench server "${DB_ARGS[@]}" --nginx --nginx-bin "${NGINX:-/usr/sbin/nginx}" "$@"
RATES="${RATES-1000,2000,3000}"
if [ -n "$RATES" ]; then
  # 10 s per rate and side unless the extra arguments give --seconds.
  SECS=(--seconds 10)
  for a in "$@"; do
    case "$a" in --seconds|--seconds=*) SECS=() ;; esac
  done
  echo "== $(date -u +%FT%TZ) uptime: $(uptime)"
  target/release/planet-bench server "${DB_ARGS[@]}" --nginx --nginx-bin "${NGINX:-/usr/sbin/nginx}" \
    --rate "$RATES" "${SECS[@]}" "$@"
fi
if [ "${LOAD:-1}" != 0 ]; then
  echo "== $(date -u +%FT%TZ) uptime: $(uptime)"
  target/release/planet-bench load "${DB_ARGS[@]}"
fi
echo "== $(date -u +%FT%TZ) uptime: $(uptime)"
