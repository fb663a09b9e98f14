#!/usr/bin/env bash
# The IO-free crates stay IO-free (issue 18): the normal dependency tree of
# the client model, the protocol and the core holds no async runtime, no
# QUIC, no TLS and no crypto. The network lives in planet-session (client)
# and planet-server. Fails, naming the crate and the dependency, otherwise.
#   scripts/check-deps.sh
set -euo pipefail
cd "$(dirname "$0")/.."
forbidden='tokio|quinn|quinn-proto|quinn-udp|rustls|ring|socket2'
status=0
for crate in planet-client planet-protocol planet-core; do
  # `cargo tree --prefix none` prints one "name vX.Y.Z ..." per line.
  tree=$(cargo tree -p "$crate" -e normal --prefix none --offline 2>/dev/null \
    || cargo tree -p "$crate" -e normal --prefix none)
  bad=$(printf '%s\n' "$tree" | awk '{print $1}' | grep -Ex "$forbidden" | sort -u || true)
  if [ -n "$bad" ]; then
    echo "check-deps: $crate depends on $(echo $bad | tr ' ' ',') (it must stay IO-free):" >&2
    for b in $bad; do cargo tree -p "$crate" -e normal -i "$b" >&2 || true; done
    status=1
  else
    echo "check-deps: $crate: no ${forbidden//|/, }"
  fi
done
# Thin binaries over single-job libraries: the renderer library carries no
# window, server, preprocessor or CLI; the server library no CLI.
check() {
  local crate=$1 forbidden=$2 why=$3 tree bad
  tree=$(cargo tree -p "$crate" -e normal --prefix none --offline 2>/dev/null \
    || cargo tree -p "$crate" -e normal --prefix none)
  bad=$(printf '%s\n' "$tree" | awk '{print $1}' | grep -Ex "$forbidden" | sort -u || true)
  if [ -n "$bad" ]; then
    echo "check-deps: $crate depends on $(echo $bad | tr ' ' ',') ($why)" >&2
    status=1
  else
    echo "check-deps: $crate: no ${forbidden//|/, }"
  fi
}
check planet-render 'winit|planet-server|planet-preprocess|planet-session|planet-linksim|tokio|clap|anyhow' \
  'the renderer library depends on core and wgpu only'
check planet-server 'clap|anyhow|tracing-subscriber|mimalloc' 'CLI dependencies belong to planet-server-bin'
exit $status
