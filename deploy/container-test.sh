#!/usr/bin/env bash
# The container image built and run as users run it, with Prometheus
# scraping it (docs/DEPLOY.md, "The container test"):
#
#  1. release binaries built on the host, a Debian base made with
#     debootstrap (cached), the image built with podman (--target
#     runtime-prebuilt);
#  2. the server run from the image (deploy/container-run.sh: uid 10001,
#     read-only root, config, TLS, tokens and databases mounted read-only),
#     time to /readyz, the probes of deploy/k8s, the image's HEALTHCHECK;
#  3. planet-view streams a database through it to convergence and compares
#     its image with one rendered from the file; a new database version is
#     rolled out (new file, symlink switched, SIGHUP) and streamed too;
#  4. Debian's Prometheus scrapes it (1 s) with a TEST copy of alerts.yml
#     (for: 5s): planet-bench load runs against the image, fault scenarios
#     (corrupt records, a file truncated in place, a tenant over its request
#     limit, refused tokens, the server stopped) push their alerts to
#     pending/firing, and every dashboard query and alert rule is evaluated;
#  5. SIGTERM with a client connected: Goodbye, exit within the manifests'
#     grace period; a config error: non-zero exit, message in the log;
#  6. deploy/check.py agree: manifests, compose file and image agree.
#
# Without podman (or root) it prints "skipped: ..." and exits 0, unless CI
# or PLANET_CI=1 is set: then that is a failure. PLANET_CACHE (default
# ~/.cache/planet) keeps the debootstrapped base between runs.
set -euo pipefail

DEPLOY="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$DEPLOY/.." && pwd)"
CACHE="${PLANET_CACHE:-${HOME:-/tmp}/.cache/planet}"
TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
IMAGE=localhost/planet-server:test
BASE=localhost/debian:bookworm-slim
SERVER=planet-ct-server
BENCH=planet-ct-bench
BROKEN=planet-ct-broken
QUIC_PORT=4433
METRICS_PORT=9100
BENCH_METRICS_PORT=9101
PROM_PORT=9190
PROM="http://127.0.0.1:$PROM_PORT"
export PLANET_CT_IMAGE="$IMAGE"

strict=0
if [ -n "${CI:-}" ] || [ "${PLANET_CI:-0}" = 1 ]; then strict=1; fi
unavailable() {
  if [ "$strict" = 1 ]; then
    echo "container test: FAIL: $1 (CI/PLANET_CI is set: the container test must run)"
    exit 1
  fi
  echo "container test: skipped: $1"
  exit 0
}
command -v podman >/dev/null 2>&1 || unavailable "podman not installed (apt-get install podman runc debootstrap)"
[ "$(id -u)" = 0 ] || unavailable "needs root (rootful podman with the runc runtime)"
for tool in debootstrap prometheus curl openssl; do
  command -v "$tool" >/dev/null 2>&1 || unavailable "$tool not installed"
done
PY="$CACHE/venv/bin/python"
[ -x "$PY" ] || PY=python3
"$PY" -c 'import yaml' 2>/dev/null || unavailable "python3 with PyYAML (run deploy/check.sh first)"
curl -sfI --max-time 20 http://deb.debian.org/debian/dists/bookworm/Release >/dev/null \
  || podman image exists "$BASE" || [ -s "$CACHE/container/debian-bookworm-minbase.tar" ] \
  || unavailable "no network to deb.debian.org and no cached base image"

now_ms() { date +%s%3N; }
secs() { awk -v ms="$1" 'BEGIN { printf "%.2f", ms / 1000 }'; }
fail() {
  echo "container test: FAIL: $*" >&2
  exit 1
}
step() { printf '\n== %s\n' "$*"; }

TMP="$(mktemp -d /tmp/planet-ct.XXXXXX)"
chmod 755 "$TMP"
pids=()
cleanup() {
  local rc=$?
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  if [ "$rc" != 0 ] && podman container exists "$SERVER" 2>/dev/null; then
    echo "--- podman logs --tail 20 $SERVER"
    podman logs --tail 20 "$SERVER" 2>&1 || true
  fi
  for c in "$SERVER" "$BENCH" "$BROKEN"; do podman rm -f -t 0 "$c" >/dev/null 2>&1 || true; done
  for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done
  rm -rf "$TMP"
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# ------------------------------------------------------------------ build
step "binaries (release: planet-server, planet-build; the clients: planet-view, planet-bench)"
t0=$(now_ms)
(cd "$ROOT" && cargo build --release --locked -q -p planet-server-bin -p planet-preprocess)
build_ms=$(( $(now_ms) - t0 ))
# The clients (planet-view, planet-bench) as ./scripts/test builds them, so
# that after its build this is a no-op (a subset of packages could resolve
# other dependency features and rebuild them).
t0=$(now_ms)
(cd "$ROOT" && cargo build --locked -q --workspace --all-targets)
echo "  release build: $(secs "$build_ms") s; debug workspace build: $(secs $(( $(now_ms) - t0 ))) s"
mkdir -p "$TMP/prebuilt"
install -s -m 0755 "$TARGET/release/planet-server" "$TARGET/release/planet-build" "$TMP/prebuilt/"

step "base image $BASE (debootstrap --variant=minbase bookworm, cached in $CACHE/container)"
t0=$(now_ms)
if ! podman image exists "$BASE"; then
  tarball="$CACHE/container/debian-bookworm-minbase.tar"
  if [ ! -s "$tarball" ]; then
    mkdir -p "$CACHE/container"
    debootstrap --variant=minbase bookworm "$TMP/rootfs" http://deb.debian.org/debian >"$TMP/debootstrap.log" 2>&1 \
      || { tail -n 20 "$TMP/debootstrap.log"; fail "debootstrap"; }
    # What the official slim image leaves out: apt caches, docs, man pages, locales.
    root="$TMP/rootfs"
    cat >"$root/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache ""; Dir::Cache::srcpkgcache "";
EOF
    cat >"$root/etc/dpkg/dpkg.cfg.d/docker" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
EOF
    rm -rf "$root"/var/cache/apt/*.bin "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* \
      "$root"/usr/share/man/* "$root"/usr/share/info/* "$root"/usr/share/locale/*
    find "$root/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
    tar -C "$root" -cf "$tarball.part" . && mv "$tarball.part" "$tarball"
    rm -rf "$root"
  fi
  podman import -q "$tarball" "$BASE" >/dev/null
fi
echo "  base ready in $(secs $(( $(now_ms) - t0 ))) s"

step "image $IMAGE (podman build --target runtime-prebuilt)"
t0=$(now_ms)
podman build -q --format docker --target runtime-prebuilt \
  --build-arg RUNTIME_IMAGE="$BASE" --build-context prebuilt="$TMP/prebuilt" \
  -t "$IMAGE" "$ROOT" >"$TMP/build.log" 2>&1 || { tail -n 30 "$TMP/build.log"; fail "podman build"; }
image_build_ms=$(( $(now_ms) - t0 ))
image_bytes=$(podman image inspect --format '{{.Size}}' "$IMAGE")
image_mb=$(awk -v b="$image_bytes" 'BEGIN { printf "%.1f", b / 1e6 }')
podman image inspect "$IMAGE" >"$TMP/image.json"
echo "  built in $(secs "$image_build_ms") s, $image_mb MB"

# ------------------------------------------------------------------ data
step "databases, TLS, tokens, server.toml"
DATA="$TMP/data"
ETC="$TMP/etc"
mkdir -p "$DATA" "$ETC"
BUILD="$TARGET/release/planet-build"
"$BUILD" build --procedural --levels 3 --seed 1 --quiet --out "$DATA/earth-v1.planetdb" >/dev/null
"$BUILD" build --procedural --levels 3 --seed 2 --quiet --out "$DATA/earth-v2.planetdb" >/dev/null
ln -s earth-v1.planetdb "$DATA/earth.planetdb"
"$PY" "$DEPLOY/ct_data.py" corrupt "$DATA/earth-v1.planetdb" "$DATA/corrupt.planetdb"
cp "$DATA/earth-v1.planetdb" "$DATA/truncated.planetdb"
"$DEPLOY/gen-dev-cert.sh" "$ETC/tls" "$ETC/tokens" >/dev/null
openssl rand -hex 32 >"$ETC/tokens/limited"
chmod 0644 "$ETC/tokens/limited" "$DATA"/*.planetdb
FP="$(openssl x509 -in "$ETC/tls/cert.pem" -outform DER | sha256sum | cut -c1-64)"
# deploy/server.toml as shipped, with the test's databases and tenants.
sed '/^\[\[database\]\]/,$d' "$DEPLOY/server.toml" >"$ETC/server.toml"
cat >>"$ETC/server.toml" <<'EOF'
[[database]]
name = "earth"
path = "/data/earth.planetdb"

[[database]]
name = "corrupt"
path = "/data/corrupt.planetdb"

[[database]]
name = "truncated"
path = "/data/truncated.planetdb"

[[tenant]]
name = "public"
token_file = "/etc/planet/tokens/public"
databases = ["earth", "corrupt", "truncated"]
max_in_flight = 64
max_bytes_per_second = 0
max_connections = 0
max_requests_per_second = 0

# A tenant held to 2 requests/s: its client runs over the limit.
[[tenant]]
name = "limited"
token_file = "/etc/planet/tokens/limited"
databases = ["earth"]
max_in_flight = 64
max_bytes_per_second = 0
max_connections = 0
max_requests_per_second = 2
EOF
find "$DATA" -mindepth 1 -printf '  %f %s bytes %l\n'

# ------------------------------------------------------------------ run
# podman without systemd cannot time the HEALTHCHECK (it says so on stderr):
# the test runs it by hand (podman healthcheck run).
start_server() {
  "$DEPLOY/container-run.sh" -d --name "$SERVER" --health-interval disable \
    -v "$DATA:/data:ro" -v "$ETC:/etc/planet:ro" \
    -- planet-server --config /etc/planet/server.toml --log-format json >/dev/null 2>>"$TMP/podman.log"
}
wait_ready() {
  local t0=$1 limit=$2
  until [ "$(curl -s -o /dev/null -w '%{http_code}' "http://127.0.0.1:$METRICS_PORT/readyz")" = 200 ]; do
    [ "$(podman inspect -f '{{.State.Running}}' "$SERVER" 2>/dev/null)" = true ] \
      || { podman logs "$SERVER" 2>&1 | tail -n 20; fail "the container stopped before /readyz answered 200"; }
    [ $(( $(now_ms) - t0 )) -lt $(( limit * 1000 )) ] || fail "/readyz not 200 within $limit s"
    sleep 0.05
  done
  echo $(( $(now_ms) - t0 ))
}

step "run the image (non-root, read-only root, read-only mounts, host network)"
for p in "$QUIC_PORT/udp" "$METRICS_PORT/tcp" "$BENCH_METRICS_PORT/tcp" "$PROM_PORT/tcp"; do
  if ss -Hln --"${p#*/}" "sport = :${p%/*}" | grep -q .; then fail "port $p is in use"; fi
done
t0=$(now_ms)
start_server
ready_ms=$(wait_ready "$t0" 60)
echo "  /readyz 200 after $(secs "$ready_ms") s (podman run to ready)"
[ "$(podman inspect -f '{{.Config.User}} {{.HostConfig.ReadonlyRootfs}}' "$SERVER")" = "10001:10001 true" ] \
  || fail "container user / read-only root: $(podman inspect -f '{{.Config.User}} {{.HostConfig.ReadonlyRootfs}}' "$SERVER")"
pid=$(podman inspect -f '{{.State.Pid}}' "$SERVER")
uid=$(awk '/^Uid:/ { print $2 }' "/proc/$pid/status")
[ "$uid" = 10001 ] || fail "planet-server runs as uid $uid, not 10001"
echo "  planet-server (host pid $pid) runs as uid $uid; read-only root filesystem"

step "probes (paths and port of deploy/k8s/deployment.yaml) and the image's HEALTHCHECK"
while read -r kind path port; do
  [ "$port" = metrics ] || [ "$port" = "$METRICS_PORT" ] || fail "$kind probe port $port"
  code=$(curl -s -o "$TMP/probe" -w '%{http_code}' "http://127.0.0.1:$METRICS_PORT$path")
  [ "$code" = 200 ] || fail "$kind probe GET $path: HTTP $code"
  echo "  $kind probe GET :$METRICS_PORT$path -> $code $(cat "$TMP/probe")"
done < <("$PY" "$DEPLOY/check.py" probes)
# The image's HEALTHCHECK has --retries=3: a container is unhealthy after
# three failed checks in a row, not one (a check's exec can exceed the 3 s
# timeout on a loaded machine).
hc=0
until podman healthcheck run "$SERVER"; do
  hc=$((hc + 1))
  [ "$hc" -lt 3 ] || fail "podman healthcheck run (the image's HEALTHCHECK) failed 3 times in a row"
  echo "  HEALTHCHECK attempt $hc failed; the image allows 3 in a row"
done
echo "  HEALTHCHECK (planet-server healthcheck inside the container): healthy"

# ------------------------------------------------------------------ Prometheus
step "Prometheus $(prometheus --version 2>&1 | awk 'NR == 1 { print $3 }') scraping the container every second"
mkdir -p "$TMP/prom"
"$PY" "$DEPLOY/promlive.py" rules-copy "$TMP/prom/alerts.yml"
echo "[{\"targets\": [\"127.0.0.1:$METRICS_PORT\"]}]" >"$TMP/prom/targets.json"
cat >"$TMP/prom/prometheus.yml" <<EOF
global:
  scrape_interval: 1s
  scrape_timeout: 1s
  evaluation_interval: 1s
rule_files: [alerts.yml]
scrape_configs:
  - job_name: planet-server
    file_sd_configs:
      - files: [targets.json]
        refresh_interval: 1s
EOF
prometheus --config.file="$TMP/prom/prometheus.yml" --storage.tsdb.path="$TMP/prom/tsdb" \
  --web.listen-address="127.0.0.1:$PROM_PORT" >"$TMP/prometheus.log" 2>&1 &
pids+=($!)
for _ in $(seq 200); do curl -sf "$PROM/-/ready" >/dev/null && break; sleep 0.1; done
curl -sf "$PROM/-/ready" >/dev/null || fail "Prometheus did not start"
value() { "$PY" "$DEPLOY/promlive.py" value "$PROM" "$1"; }
until [ "$(value 'up{job="planet-server"}')" = 1 ]; do sleep 0.5; done
echo "  target up"

# ------------------------------------------------------------------ streaming
# view NAME DB [planet-view args...]: planet-view render through the container.
# VIEW_TRAJECTORY (default static-low), VIEW_LOG (RUST_LOG, default warn);
# VIEW_BG=1 runs it in the background: its pid is then $view_pid.
view() {
  local name=$1 db=$2
  shift 2
  local cmd=("$TARGET/debug/planet-view" render --server "127.0.0.1:$QUIC_PORT" --fingerprint "$FP"
    --database "$db" --trajectory "${VIEW_TRAJECTORY:-static-low}" --width 320 --height 240
    --out "$TMP/$name" "$@")
  if [ "${VIEW_BG:-0}" = 1 ]; then
    RUST_LOG="${VIEW_LOG:-warn}" "${cmd[@]}" &
    view_pid=$!
    pids+=("$view_pid")
  else
    RUST_LOG="${VIEW_LOG:-warn}" "${cmd[@]}"
  fi
}
ok_records() { value "sum(planet_requests_total{outcome=\"ok\",tenant=\"public\",database=\"earth\"})"; }
converge() {
  local name=$1 ref=$2 before out
  mkdir -p "$TMP/$name"
  before=$(ok_records)
  view "$name" earth --token "$(cat "$ETC/tokens/public")" --duration 12 --fps 2 --reference-db "$ref" \
    >"$TMP/$name.out" 2>"$TMP/$name.err" || { cat "$TMP/$name.err"; fail "planet-view render ($name)"; }
  sleep 2
  out=$(grep '^image error' "$TMP/$name.out") || fail "no image error line"
  echo "  $(grep '^planet-view render' "$TMP/$name.out" | sed 's/; CSV.*//')"
  echo "  $out"
  "$PY" "$DEPLOY/ct_data.py" converged "$TMP/$name/frames.csv" || fail "$name: not converged to the database file"
  echo $(( $(ok_records | cut -d. -f1) - ${before%.*} )) >"$TMP/$name.records"
}

step "planet-view streams earth (v1) through the container to convergence"
converge view-v1 "$DATA/earth-v1.planetdb"
records_v1=$(cat "$TMP/view-v1.records")
echo "  records served (planet_requests_total ok, tenant public): $records_v1"

step "roll out a new version: new file, symlink switched atomically, SIGHUP"
ln -s earth-v2.planetdb "$DATA/earth.planetdb.next"
mv -T "$DATA/earth.planetdb.next" "$DATA/earth.planetdb"
podman kill --signal HUP "$SERVER" >/dev/null
for _ in $(seq 50); do [ "$(value 'planet_database_reloads_total{database="earth"}')" = 1 ] && break; sleep 0.2; done
[ "$(value 'planet_database_reloads_total{database="earth"}')" = 1 ] || fail "no reload counted"
size=$(value 'planet_database_size_bytes{database="earth"}')
[ "$size" = "$(stat -c %s "$DATA/earth-v2.planetdb")" ] || fail "database size $size is not the new file's"
echo "  reloaded; planet_database_size_bytes = $size (earth-v2.planetdb)"
converge view-v2 "$DATA/earth-v2.planetdb"
records_v2=$(cat "$TMP/view-v2.records")

# ------------------------------------------------------------------ load
step "planet-bench load against the image (a second container: the bench's own server arguments)"
echo "[{\"targets\": [\"127.0.0.1:$METRICS_PORT\", \"127.0.0.1:$BENCH_METRICS_PORT\"]}]" >"$TMP/prom/targets.json"
LOAD_CLIENTS=50
LOAD_SECONDS=15
t0=$(now_ms)
PLANET_CT_NAME=$BENCH PLANET_CT_METRICS="127.0.0.1:$BENCH_METRICS_PORT" \
  "$TARGET/debug/planet-bench" load --server-bin "$DEPLOY/container-run.sh" --clients "$LOAD_CLIENTS" \
  --seconds "$LOAD_SECONDS" --db "$DATA/earth-v1.planetdb" >"$TMP/load.out" 2>&1 \
  || { cat "$TMP/load.out"; fail "planet-bench load"; }
load_s=$(( ($(now_ms) - t0) / 1000 + 5 ))
podman rm -f -t 0 "$BENCH" >/dev/null 2>&1 || true
grep -E '^ +(clients|requests|server)' "$TMP/load.out" | head -n 6 | sed 's/^ */  /' || true
bench_inst="instance=\"127.0.0.1:$BENCH_METRICS_PORT\""
load_records=$(value "sum(max_over_time(planet_requests_total{$bench_inst,outcome=\"ok\"}[${load_s}s]))")
rss_idle=$(value "min_over_time(process_resident_memory_bytes{$bench_inst}[${load_s}s])")
rss_peak=$(value "max_over_time(process_resident_memory_bytes{$bench_inst}[${load_s}s])")
conns_peak=$(value "max_over_time(planet_connections_active{$bench_inst}[${load_s}s])")
per_conn_kib=$(awk -v a="$rss_idle" -v b="$rss_peak" -v n="$conns_peak" 'BEGIN { printf "%.1f", (b - a) / n / 1024 }')
echo "  records served to the load clients: ${load_records%.*}; connections at peak ${conns_peak%.*}"
echo "  container RSS (process_resident_memory_bytes) first scrape $(( ${rss_idle%.*} / 1048576 )) MiB," \
  "peak $(( ${rss_peak%.*} / 1048576 )) MiB: $per_conn_kib KiB per connection"
echo "[{\"targets\": [\"127.0.0.1:$METRICS_PORT\"]}]" >"$TMP/prom/targets.json"

# ------------------------------------------------------------------ faults
step "faults: each pushes its alert to pending/firing (TEST copy of the rules, for: 5s)"
alert() { "$PY" "$DEPLOY/promlive.py" alert "$PROM" "$1" "$2" || fail "alert $1"; }
# fault NAME DB TENANT TOKEN SECONDS [ARGS...]: a client of TENANT streaming DB.
fault() {
  local name=$1 db=$2 tenant=$3 token=$4 seconds=$5
  shift 5
  mkdir -p "$TMP/$name"
  view "$name" "$db" --tenant "$tenant" --token "$token" --duration "$seconds" --fps 2 "$@" \
    >"$TMP/$name.out" 2>"$TMP/$name.err" || true
}
echo "  tenant over its limit: tenant limited (2 requests/s) flies an orbit over earth"
VIEW_TRAJECTORY=orbit fault f-limited earth limited "$(cat "$ETC/tokens/limited")" 12 --max-sse 0.05
alert PlanetServerRateLimiting 40
echo "  corrupt records: planet-view streams corrupt.planetdb (every record's checksum broken) while"
echo "  another flies an orbit over earth (PlanetServerHighErrorRate needs more than 1 request/s)"
VIEW_BG=1 VIEW_TRAJECTORY=orbit fault f-orbit earth public "$(cat "$ETC/tokens/public")" 20 --max-sse 0.05
orbit_view=$view_pid
fault f-corrupt corrupt public "$(cat "$ETC/tokens/public")" 6
alert PlanetDatabaseCorruptRecords 30
alert PlanetServerHighErrorRate 40
wait "$orbit_view" || true
echo "  storage: truncated.planetdb truncated in place under the running server, then streamed"
truncate -s 4096 "$DATA/truncated.planetdb"
fault f-storage truncated public "$(cat "$ETC/tokens/public")" 6
alert PlanetServerStorageErrors 30
# What the alert says to do: republish the file by rename, SIGHUP.
cp "$DATA/earth-v1.planetdb" "$DATA/truncated.planetdb.next"
mv "$DATA/truncated.planetdb.next" "$DATA/truncated.planetdb"
podman kill --signal HUP "$SERVER" >/dev/null
for _ in $(seq 50); do [ "$(value 'planet_database_reloads_total{database="truncated"}')" = 1 ] && break; sleep 0.2; done
[ "$(value 'planet_database_reloads_total{database="truncated"}')" = 1 ] || fail "truncated.planetdb: republished file not reloaded"
echo "  republished by rename + SIGHUP: reloaded"
echo "  refused token: a client of tenant public with a wrong token"
fault f-token earth public "wrong-token-$(openssl rand -hex 16)" 2
grep -qi unauthorized "$TMP/f-token.err" || { cat "$TMP/f-token.err"; fail "the wrong token was not refused"; }
[ "$(value 'planet_handshakes_total{outcome="unauthorized"}')" != 0 ] || fail "no unauthorized handshake counted"
echo "  refused: unauthorized (planet_handshakes_total{outcome=\"unauthorized\"} $(value 'planet_handshakes_total{outcome="unauthorized"}'))"

step "SIGTERM with a client connected (then the server restarted)"
mkdir -p "$TMP/drain"
VIEW_BG=1 VIEW_LOG=planet_session=info VIEW_TRAJECTORY=orbit view drain earth --token "$(cat "$ETC/tokens/public")" \
  --duration 60 --fps 2 --max-sse 0.05 >"$TMP/drain.out" 2>"$TMP/drain.err"
drain_view=$view_pid
for _ in $(seq 100); do
  [ "$(curl -s "http://127.0.0.1:$METRICS_PORT/metrics" | awk '$1 == "planet_connections_active" { print $2 }')" -ge 1 ] 2>/dev/null && break
  sleep 0.1
done
sleep 2
in_flight=$(curl -s "http://127.0.0.1:$METRICS_PORT/metrics" | awk '$1 == "planet_requests_in_flight" { print $2 }')
# Every record the container served before it is stopped (the counters restart with it).
served=$(value "sum(planet_requests_total{instance=\"127.0.0.1:$METRICS_PORT\",outcome=\"ok\"})")
grace=$("$PY" "$DEPLOY/check.py" grace)
t0=$(now_ms)
podman stop -t "$grace" "$SERVER" >/dev/null 2>>"$TMP/podman.log"
drain_ms=$(( $(now_ms) - t0 ))
exit_code=$(podman inspect -f '{{.State.ExitCode}}' "$SERVER")
sleep 1
kill "$drain_view" 2>/dev/null || true
wait "$drain_view" 2>/dev/null || true
goodbye=$(sed 's/\x1b\[[0-9;]*m//g' "$TMP/drain.err" | grep -m1 'server said goodbye' || true)
case "$goodbye" in
  *shutting_down*) ;;
  *) tail -n 20 "$TMP/drain.err"; fail "the connected client got no Goodbye{shutting_down}" ;;
esac
[ "$exit_code" = 0 ] || fail "exit code $exit_code after SIGTERM"
[ "$drain_ms" -lt $(( grace * 1000 )) ] || fail "drain took $(secs "$drain_ms") s, grace period $grace s"
echo "  client: ${goodbye#*INFO }"
echo "  stopped in $(secs "$drain_ms") s ($in_flight requests in flight just before; grace period of the manifests: $grace s), exit code $exit_code"
podman logs "$SERVER" >"$TMP/server.log" 2>&1 || true
grep -q 'draining connections' "$TMP/server.log" || fail "no drain in the server log"
alert PlanetServerDown 30
alert PlanetServerAllReplicasDown 30
t0=$(now_ms)
podman start "$SERVER" >/dev/null 2>>"$TMP/podman.log"
restart_ms=$(wait_ready "$t0" 60)
until [ "$(value 'up{job="planet-server"}')" = 1 ]; do sleep 0.5; done
echo "  restarted: /readyz 200 after $(secs "$restart_ms") s"
converge view-restart "$DATA/earth-v2.planetdb"
records_restart=$(cat "$TMP/view-restart.records")
records=$(( ${served%.*} + ${load_records%.*} + records_restart ))

# ------------------------------------------------------------------ evaluate
step "every dashboard query and alert rule against Prometheus"
"$PY" "$DEPLOY/promlive.py" eval "$PROM" | tee "$TMP/eval.out" || fail "a dashboard or alert expression returned no data"
exprs=$(sed -n 's/^expressions: //p' "$TMP/eval.out")

step "a config error: non-zero exit, the reason in the container log"
cp "$ETC/server.toml" "$TMP/broken.toml"
sed -i 's/^databases = \["earth"\]$/databases = ["earth", "moon"]/' "$TMP/broken.toml"
grep -q '"moon"' "$TMP/broken.toml" || fail "could not break the config"
if "$DEPLOY/container-run.sh" --name "$BROKEN" -v "$DATA:/data:ro" -v "$ETC:/etc/planet:ro" \
  -v "$TMP/broken.toml:/etc/planet/server.toml:ro" \
  -- planet-server --config /etc/planet/server.toml --log-format json >/dev/null 2>&1; then
  fail "the server started with a tenant naming an unknown database"
fi
broken_rc=$(podman inspect -f '{{.State.ExitCode}}' "$BROKEN")
broken_log=$(podman logs "$BROKEN" 2>&1 | grep -m1 'planet-server: error' || true)
if [ "$broken_rc" = 0 ] || [ -z "$broken_log" ]; then
  fail "config error: exit $broken_rc, log: $(podman logs "$BROKEN" 2>&1 | tail -n 3)"
fi
echo "  exit code $broken_rc; log: $broken_log"

step "manifests, compose file and image agree"
"$PY" "$DEPLOY/check.py" agree "$TMP/image.json" "$per_conn_kib" "$drain_ms" || fail "deploy/check.py agree"

step "summary"
cat <<EOF
container test: passed
  image size:                  $image_mb MB ($IMAGE, podman image inspect .Size)
  release build, image build:  $(secs "$build_ms") s, $(secs "$image_build_ms") s
  start-up time to ready:      $(secs "$ready_ms") s (podman run to /readyz 200); $(secs "$restart_ms") s after a restart
  records streamed through it: $records served ok (planet_requests_total): ${served%.*} by the server container before SIGTERM
                               (converged planet-view sessions: $records_v1 of v1, $records_v2 of v2; orbits; the limited tenant),
                               ${load_records%.*} by the load container to $LOAD_CLIENTS planet-bench clients, $records_restart after the restart
  drain time on SIGTERM:       $(secs "$drain_ms") s with a client streaming ($in_flight requests in flight; Goodbye received; grace period $grace s)
  memory per connection:       $per_conn_kib KiB (container RSS, $LOAD_CLIENTS load clients)
  expressions evaluated:       $exprs
EOF
