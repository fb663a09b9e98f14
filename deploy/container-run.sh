#!/usr/bin/env bash
# Runs the planet-server image as deploy/compose.yaml and deploy/k8s run it:
# uid 10001, read-only root filesystem, no capabilities, no privilege gain,
# a tmpfs /tmp; the host's network (podman here has no other working one).
#
#   deploy/container-run.sh [PODMAN-RUN-OPTIONS...] -- [COMMAND...]
#       e.g. -d --name X -v DIR:/data:ro -- planet-server --config ...
#   deploy/container-run.sh --database DB [PLANET-SERVER-ARGS...]
#       as `planet-bench load --server-bin`: planet-server's own arguments;
#       the --database file's directory is mounted read-only at /data,
#       PLANET_CT_METRICS adds --metrics ADDR, PLANET_CT_NAME names the
#       container (default planet-ct-bench).
#
# PLANET_CT_IMAGE: the image (default localhost/planet-server:test).
set -euo pipefail
image="${PLANET_CT_IMAGE:-localhost/planet-server:test}"
hardened=(--network host --read-only --user 10001:10001 --cap-drop ALL
  --security-opt no-new-privileges:true --tmpfs /tmp)

if [ "${1:-}" = --database ]; then
  args=()
  mounts=()
  while [ $# -gt 0 ]; do
    if [ "$1" = --database ] && [ $# -ge 2 ]; then
      db="$(realpath "$2")"
      mounts+=(-v "$(dirname "$db"):/data:ro")
      args+=(--database "/data/$(basename "$db")")
      shift 2
    else
      args+=("$1")
      shift
    fi
  done
  if [ -n "${PLANET_CT_METRICS:-}" ]; then
    args+=(--metrics "$PLANET_CT_METRICS")
  fi
  exec podman run --rm --name "${PLANET_CT_NAME:-planet-ct-bench}" "${hardened[@]}" \
    -e RUST_LOG "${mounts[@]}" "$image" planet-server "${args[@]}"
fi

opts=()
while [ $# -gt 0 ] && [ "$1" != -- ]; do
  opts+=("$1")
  shift
done
[ "${1:-}" = -- ] && shift
exec podman run "${hardened[@]}" "${opts[@]}" "$image" "$@"
