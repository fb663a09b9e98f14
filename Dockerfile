# syntax=docker/dockerfile:1
#
# planet-server image: the multi-tenant QUIC server (planet-server) and the
# database builder (planet-build). See docs/DEPLOY.md.
#
#   docker build -t planet-server:dev .
#   docker run --rm -p 4433:4433/udp -p 9100:9100 \
#     -v "$PWD/deploy/data:/data:ro" \
#     -v "$PWD/deploy/server.toml:/etc/planet/server.toml:ro" \
#     -v "$PWD/deploy/tls:/etc/planet/tls:ro" planet-server:dev
#
# Without a registry (how deploy/container-test.sh builds it): binaries built
# on the host, a base image made with debootstrap:
#
#   podman build --target runtime-prebuilt \
#     --build-arg RUNTIME_IMAGE=localhost/debian:bookworm-slim \
#     --build-context prebuilt=DIR_WITH_planet-server_AND_planet-build \
#     -t planet-server:dev .

# Base images (override with --build-arg, e.g. a mirror or a local import).
ARG RUST_IMAGE=rust:1-bookworm
ARG RUNTIME_IMAGE=debian:bookworm-slim

############################ builder ############################
FROM ${RUST_IMAGE} AS builder
WORKDIR /src

# The whole workspace is needed: cargo resolves every member listed in the
# root Cargo.toml even when building only two packages. .dockerignore keeps
# target/, .git and databases out of the context.
COPY . .

# BuildKit cache mounts keep the registry and target dir between builds; the
# binaries are copied out of the cached target dir in the same step.
RUN --mount=type=cache,id=planet-cargo-registry,target=/usr/local/cargo/registry \
    --mount=type=cache,id=planet-target,target=/src/target \
    cargo build --release --locked -p planet-server-bin -p planet-preprocess \
 && install -D -s -m 0755 target/release/planet-server /out/planet-server \
 && install -D -s -m 0755 target/release/planet-build /out/planet-build

############################ runtime ############################
# Everything of the runtime image except the binaries; the two stages below
# add them, from the builder stage (the default target, last in this file)
# or from a build context named "prebuilt" (runtime-prebuilt).
FROM ${RUNTIME_IMAGE} AS runtime-base

ARG VERSION=dev
LABEL org.opencontainers.image.title="planet-server" \
      org.opencontainers.image.description="Multi-tenant QUIC server of memory-mapped planet databases" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.licenses="MIT OR Apache-2.0"

# ca-certificates only: TLS roots for anything that verifies a peer. Nothing
# else is installed (no shell tools are needed by the server).
# hadolint ignore=DL3008
RUN apt-get update \
 && apt-get install -y --no-install-recommends ca-certificates \
 && rm -rf /var/lib/apt/lists/*

RUN groupadd --system --gid 10001 planet \
 && useradd --system --uid 10001 --gid planet --no-create-home \
      --home-dir /nonexistent --shell /usr/sbin/nologin planet \
 && mkdir -p /data /etc/planet

# /data: database files (*.planetdb), mounted read-only.
# /etc/planet: server.toml, tls/, tokens/, mounted read-only.
VOLUME ["/data", "/etc/planet"]

# 4433/udp: QUIC (planet protocol). 9100/tcp: /metrics, /healthz, /readyz.
EXPOSE 4433/udp 9100/tcp

ENV RUST_LOG=info

USER 10001:10001

# The server binary has a tiny HTTP GET client for this, so the image needs
# no curl. It exits 0 when /healthz answers 200, 1 otherwise.
HEALTHCHECK --interval=15s --timeout=3s --start-period=20s --retries=3 \
  CMD ["planet-server", "healthcheck", "--url", "http://127.0.0.1:9100/healthz"]

CMD ["planet-server", "--config", "/etc/planet/server.toml"]

# Binaries built on the host (release, stripped), e.g. where no Rust image
# can be pulled: --build-context prebuilt=DIR --target runtime-prebuilt.
FROM runtime-base AS runtime-prebuilt
# "prebuilt" is a named build context (--build-context), not a stage.
# hadolint ignore=DL3022
COPY --from=prebuilt planet-server planet-build /usr/local/bin/

# The default target: binaries from the builder stage.
FROM runtime-base AS runtime
COPY --from=builder /out/planet-server /out/planet-build /usr/local/bin/
