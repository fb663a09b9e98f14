//! TLS for the QUIC endpoint: certificates from PEM files or a generated
//! development certificate, rustls with the ring provider only, ALPN
//! `planet/1`, TLS 1.3 only (QUIC requires it).
//!
//! **0-RTT is disabled** (`max_early_data_size = 0`): requests are idempotent
//! reads, but a replayed 0-RTT `Hello` would let an on-path attacker re-run
//! authentication and consume a tenant's connection and bandwidth budget,
//! while the saving (one round trip per connection, not per request) is
//! negligible for long-lived streaming sessions.

use std::path::Path;
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

/// TLS setup failures.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// A PEM file could not be read or parsed.
    #[error("cannot load {what} from {path}: {reason}")]
    Pem {
        /// `certificate` or `private key`.
        what: &'static str,
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
    /// Generating the development certificate failed.
    #[error("cannot generate a development certificate: {0}")]
    DevCert(String),
    /// rustls or quinn refused the configuration.
    #[error("invalid TLS configuration: {0}")]
    Config(String),
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
            .map_err(|e| TlsError::Pem {
                what: "certificate",
                path: cert.display().to_string(),
                reason: e.to_string(),
            })?;
        if chain.is_empty() {
            return Err(TlsError::Pem {
                what: "certificate",
                path: cert.display().to_string(),
                reason: "no CERTIFICATE block".into(),
            });
        }
        let key = PrivateKeyDer::from_pem_file(key).map_err(|e| TlsError::Pem {
            what: "private key",
            path: key.display().to_string(),
            reason: e.to_string(),
        })?;
        Ok(CertKey { chain, key })
    }

    /// A self-signed certificate for `localhost` and `127.0.0.1`.
    pub fn dev_cert() -> Result<CertKey, TlsError> {
        let ck = rcgen::generate_simple_self_signed(vec![
            "localhost".to_string(),
            "127.0.0.1".to_string(),
        ])
        .map_err(|e| TlsError::DevCert(e.to_string()))?;
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

/// The rustls server configuration: ring, TLS 1.3, ALPN `planet/1`, no 0-RTT.
pub fn rustls_server_config(ck: &CertKey) -> Result<rustls::ServerConfig, TlsError> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut cfg = rustls::ServerConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| TlsError::Config(e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(ck.chain.clone(), ck.key.clone_key())
        .map_err(|e| TlsError::Config(e.to_string()))?;
    cfg.alpn_protocols = vec![planet_protocol::ALPN.to_vec()];
    cfg.max_early_data_size = 0;
    Ok(cfg)
}
