#!/usr/bin/env bash
# Writes a self-signed certificate and key for local runs of compose.yaml:
#   deploy/tls/cert.pem, deploy/tls/key.pem  (CN/SAN: localhost, 127.0.0.1, ::1)
# and, if missing, a random token for the tenant "public": deploy/tokens/public.
#   deploy/gen-dev-cert.sh [TLS_DIR [TOKENS_DIR]]   (defaults: deploy/tls, deploy/tokens)
# Clients must trust deploy/tls/cert.pem (or run in their insecure/dev mode).
# Never use these in production.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
out="${1:-$here/tls}"
mkdir -p "$out"
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
  -days 30 -subj "/CN=localhost" \
  -addext "subjectAltName=DNS:localhost,DNS:planet-server,IP:127.0.0.1,IP:::1" \
  -keyout "$out/key.pem" -out "$out/cert.pem" 2>/dev/null
# The container runs as uid 10001: the key must be readable by it.
chmod 0644 "$out/cert.pem"
chmod 0644 "$out/key.pem"
echo "wrote $out/cert.pem and $out/key.pem"
tokens="${2:-$here/tokens}"
if [ ! -s "$tokens/public" ]; then
  mkdir -p "$tokens"
  openssl rand -hex 32 > "$tokens/public"
  chmod 0644 "$tokens/public"   # read by uid 10001 in the container
  echo "wrote $tokens/public (clients send it as the tenant \"public\" token)"
fi
