//! TLS for the client transport: rustls (ring provider only, TLS 1.3, ALPN
//! `planet/1`) configured either to **pin** the server certificate by its
//! SHA-256 fingerprint (what `planet-server --dev-cert` prints), or to trust
//! given CA / self-signed certificates (normal WebPKI name checks).
//!
//! Pinning replaces chain and name validation: the server is accepted if and
//! only if its end-entity certificate has exactly the pinned hash. The
//! handshake signatures are still verified against that certificate's key
//! with ring's algorithms, so a peer that merely replays the certificate
//! without the private key is refused.

use std::sync::Arc;

use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::{CryptoProvider, WebPkiSupportedAlgorithms};
use rustls::pki_types::{CertificateDer, ServerName, UnixTime};
use rustls::{DigitallySignedStruct, SignatureScheme};

/// TLS configuration errors.
#[derive(Debug, Clone, thiserror::Error)]
pub enum TlsError {
    /// The fingerprint is not 64 hex digits (colons allowed).
    #[error("invalid SHA-256 fingerprint {0:?}: expected 64 hex digits")]
    BadFingerprint(String),
    /// A trusted certificate was refused by the root store.
    #[error("cannot trust certificate")]
    BadCertificate(#[source] rustls::Error),
    /// rustls refused the configuration.
    #[error("invalid TLS configuration")]
    Config(#[source] rustls::Error),
    /// No root certificate could be loaded from the system.
    #[error("no system root certificates ({0})")]
    NoSystemRoots(String),
}

/// How the client authenticates the server.
#[derive(Debug, Clone)]
pub enum ServerTrust {
    /// Accept only the certificate with this SHA-256 (of its DER).
    Fingerprint([u8; 32]),
    /// Trust these CA (or self-signed) certificates, DER encoded, with the
    /// usual name checks against the server name given at connect time.
    Certificates(Vec<Vec<u8>>),
    /// Trust the operating system's root certificates (a public HTTPS
    /// server, object store or CDN).
    System,
}

/// Installs ring as the process-wide rustls provider (idempotent). The
/// configurations below pass the provider explicitly and do not need it, but
/// other rustls users in the process may.
pub fn install_crypto_provider() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// SHA-256 of `der`.
pub fn sha256(der: &[u8]) -> [u8; 32] {
    let d = ring::digest::digest(&ring::digest::SHA256, der);
    let mut out = [0u8; 32];
    out.copy_from_slice(d.as_ref());
    out
}

/// Lower-case hex SHA-256 of `der` (same format as the server prints).
pub fn sha256_hex(der: &[u8]) -> String {
    sha256(der).iter().map(|b| format!("{b:02x}")).collect()
}

/// Parses a fingerprint: 64 hex digits, optionally separated by `:`.
pub fn parse_fingerprint(s: &str) -> Result<[u8; 32], TlsError> {
    let hex: Vec<u8> = s.trim().bytes().filter(|&b| b != b':').collect();
    if hex.len() != 64 {
        return Err(TlsError::BadFingerprint(s.to_string()));
    }
    let mut out = [0u8; 32];
    for (i, pair) in hex.chunks_exact(2).enumerate() {
        let text = std::str::from_utf8(pair).map_err(|_| TlsError::BadFingerprint(s.into()))?;
        out[i] = u8::from_str_radix(text, 16).map_err(|_| TlsError::BadFingerprint(s.into()))?;
    }
    Ok(out)
}

/// Accepts exactly one certificate (by SHA-256), verifies signatures with
/// the provider's algorithms.
#[derive(Debug)]
struct PinnedVerifier {
    fingerprint: [u8; 32],
    algorithms: WebPkiSupportedAlgorithms,
}

impl ServerCertVerifier for PinnedVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        if sha256(end_entity.as_ref()) == self.fingerprint {
            Ok(ServerCertVerified::assertion())
        } else {
            Err(rustls::Error::InvalidCertificate(
                rustls::CertificateError::ApplicationVerificationFailure,
            ))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(message, cert, dss, &self.algorithms)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(message, cert, dss, &self.algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.algorithms.supported_schemes()
    }
}

fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// A rustls client configuration for the planet protocol (TLS 1.3, ALPN
/// `planet/1`, ring) with the given trust.
pub fn client_config(trust: &ServerTrust) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    let mut cfg = build(trust, &[&rustls::version::TLS13])?;
    cfg.alpn_protocols = vec![planet_protocol::ALPN.to_vec()];
    // 0-RTT: a resumed session may carry the Hello as early data
    // (`ConnectOptions::zero_rtt`); the session tickets are kept in this
    // configuration's in-memory resumption store, shared by every
    // connection made with it.
    cfg.enable_early_data = true;
    Ok(Arc::new(cfg))
}

/// A rustls client configuration for HTTPS servers (the HTTP/2 transport,
/// [`crate::http`]): TLS 1.3 or 1.2 (many static hosts still default to
/// 1.2: nginx before 1.23.4), ALPN `h2` (the HTTP session offers `http/1.1` too), ring, with the given trust.
pub fn https_config(trust: &ServerTrust) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    let mut cfg = build(trust, &[&rustls::version::TLS13, &rustls::version::TLS12])?;
    cfg.alpn_protocols = vec![b"h2".to_vec()];
    Ok(Arc::new(cfg))
}

fn build(
    trust: &ServerTrust,
    versions: &[&'static rustls::SupportedProtocolVersion],
) -> Result<rustls::ClientConfig, TlsError> {
    let provider = provider();
    let builder = rustls::ClientConfig::builder_with_provider(Arc::clone(&provider))
        .with_protocol_versions(versions)
        .map_err(TlsError::Config)?;
    let cfg = match trust {
        ServerTrust::Fingerprint(fp) => builder
            .dangerous()
            .with_custom_certificate_verifier(Arc::new(PinnedVerifier {
                fingerprint: *fp,
                algorithms: provider.signature_verification_algorithms,
            }))
            .with_no_client_auth(),
        ServerTrust::Certificates(ders) => {
            let mut roots = rustls::RootCertStore::empty();
            for der in ders {
                roots
                    .add(CertificateDer::from(der.clone()))
                    .map_err(TlsError::BadCertificate)?;
            }
            builder.with_root_certificates(roots).with_no_client_auth()
        }
        ServerTrust::System => {
            let found = rustls_native_certs::load_native_certs();
            let mut roots = rustls::RootCertStore::empty();
            let (added, _) = roots.add_parsable_certificates(found.certs);
            if added == 0 {
                let why = found
                    .errors
                    .first()
                    .map_or("none found".to_string(), |e| e.to_string());
                return Err(TlsError::NoSystemRoots(why));
            }
            builder.with_root_certificates(roots).with_no_client_auth()
        }
    };
    Ok(cfg)
}

/// Pins the server certificate by its hex SHA-256 fingerprint.
pub fn pinned(fingerprint_hex: &str) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    client_config(&ServerTrust::Fingerprint(parse_fingerprint(
        fingerprint_hex,
    )?))
}

/// Trusts the given CA or self-signed certificate (DER).
pub fn trusting(cert_der: &[u8]) -> Result<Arc<rustls::ClientConfig>, TlsError> {
    client_config(&ServerTrust::Certificates(vec![cert_der.to_vec()]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_parsing() {
        let hex = "00".repeat(31) + "ff";
        assert_eq!(parse_fingerprint(&hex).unwrap()[31], 0xff);
        let colons: Vec<String> = (0..32).map(|i| format!("{i:02X}")).collect();
        assert_eq!(parse_fingerprint(&colons.join(":")).unwrap()[5], 5);
        assert!(parse_fingerprint("abc").is_err());
        assert!(parse_fingerprint(&"zz".repeat(32)).is_err());
        assert_eq!(sha256_hex(b"").len(), 64);
    }
}
