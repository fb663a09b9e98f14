//! TLS for the QUIC endpoint: certificates from PEM files or a generated
//! development certificate, rustls with the ring provider only, ALPN
//! `planet/1`, TLS 1.3 only (QUIC requires it).
//!
//! **0-RTT** (`zero_rtt`, on by default): a client resuming a TLS session
//! may send its `Hello` in 0-RTT and get the `Welcome` in 0.5-RTT, one round
//! trip after its first packet instead of two. Replays are refused: session
//! tickets are stateful (no ticketer) and rustls takes them out of the
//! session cache on use (`StoresServerSessions::take`), so a captured 0-RTT
//! flight replayed to this server finds its ticket gone and falls back to a
//! full handshake the attacker cannot complete. Requests are idempotent reads
//! in any case. With `zero_rtt = false` early data is refused
//! (`max_early_data_size = 0`).

use std::path::Path;
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

/// TLS setup failures.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A PEM file could not be read or parsed.
    #[error("cannot load {what} from {path}")]
    Pem {
        /// `certificate` or `private key`.
        what: &'static str,
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: rustls::pki_types::pem::Error,
    },
    /// A PEM file holds no certificate.
    #[error("no CERTIFICATE block in {path}")]
    NoCertificate {
        /// The file.
        path: String,
    },
    /// Generating the development certificate failed.
    #[error("cannot generate a development certificate")]
    DevCert(#[source] rcgen::Error),
    /// rustls refused the configuration.
    #[error("invalid TLS configuration")]
    Config(#[source] rustls::Error),
    /// quinn refused the rustls configuration (no initial cipher suite).
    #[error("invalid QUIC TLS configuration")]
    Quic(#[source] quinn::crypto::rustls::NoInitialCipherSuite),
}

/// A certificate chain and its key.
pub struct CertKey {
    /// Chain, end-entity first.
    pub chain: Vec<CertificateDer<'static>>,
    /// Private key.
    pub key: PrivateKeyDer<'static>,
}

impl CertKey {
    /// Loads a PEM certificate chain and key.
    pub fn from_pem_files(cert: &Path, key: &Path) -> Result<CertKey, TlsError> {
        let chain: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(cert)
            .and_then(|it| it.collect::<Result<Vec<_>, _>>())
            .map_err(|source| TlsError::Pem {
                what: "certificate",
                path: cert.display().to_string(),
                source,
            })?;
        if chain.is_empty() {
            return Err(TlsError::NoCertificate {
                path: cert.display().to_string(),
            });
        }
        let key = PrivateKeyDer::from_pem_file(key).map_err(|source| TlsError::Pem {
            what: "private key",
            path: key.display().to_string(),
            source,
        })?;
        Ok(CertKey { chain, key })
    }

    /// A self-signed certificate for `localhost` and `127.0.0.1`.
    pub fn dev_cert() -> Result<CertKey, TlsError> {
        let ck = rcgen::generate_simple_self_signed(vec![
            "localhost".to_string(),
            "127.0.0.1".to_string(),
        ])
        .map_err(TlsError::DevCert)?;
        let key = PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(ck.signing_key.serialize_der()));
        Ok(CertKey {
            chain: vec![ck.cert.der().clone()],
            key,
        })
    }

    /// DER of the end-entity certificate.
    pub fn leaf_der(&self) -> &[u8] {
        self.chain.first().map(|c| c.as_ref()).unwrap_or(&[])
    }
}

/// Lower-case hex SHA-256 of `der` (the certificate fingerprint clients pin).
pub fn sha256_hex(der: &[u8]) -> String {
    let digest = ring::digest::digest(&ring::digest::SHA256, der);
    digest.as_ref().iter().map(|b| format!("{b:02x}")).collect()
}

/// Installs ring as the process-wide rustls provider (idempotent).
pub fn install_crypto_provider() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// Resumable sessions kept per server: stateful tickets, about 450 bytes
/// each in the 2-hour soak (docs/BENCHMARKS.md "Soak"), so at most about
/// 3.5 MiB. Older ones are evicted: their clients do a full handshake.
pub const SESSION_CACHE_SIZE: usize = 8192;

/// Session tickets sent after each handshake: rustls's default of 2, kept
/// on purpose. A client spends a ticket on every connection attempt, even
/// one that never reaches the server, so after a dropped link the second
/// ticket is what lets a reconnect that follows a failed attempt still
/// send its Hello in 0-RTT (`server` session_reconnects_after_server_restart
/// fails with 1).
pub const TICKETS_PER_CONNECTION: usize = 2;

/// The rustls server configuration: ring, TLS 1.3, ALPN `planet/1`, stateful
/// single-use session tickets, early data (0-RTT) if `zero_rtt`.
pub fn rustls_server_config(
    ck: &CertKey,
    zero_rtt: bool,
) -> Result<rustls::ServerConfig, TlsError> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut cfg = rustls::ServerConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(TlsError::Config)?
        .with_no_client_auth()
        .with_single_cert(ck.chain.clone(), ck.key.clone_key())
        .map_err(TlsError::Config)?;
    cfg.alpn_protocols = vec![planet_protocol::ALPN.to_vec()];
    cfg.session_storage = rustls::server::ServerSessionMemoryCache::new(SESSION_CACHE_SIZE);
    cfg.send_tls13_tickets = TICKETS_PER_CONNECTION;
    // QUIC allows only 0 or u32::MAX (RFC 9001 §4.6.1).
    cfg.max_early_data_size = if zero_rtt { u32::MAX } else { 0 };
    Ok(cfg)
}
