//! Tenant bearer tokens, kept only as SHA-256 hashes (docs/SECURITY.md,
//! "Tokens").
//!
//! A [`Token`] is built from the configured secret and keeps its SHA-256
//! hash and the result of the strength checks, never the secret itself, so
//! neither `Debug`, a log line nor a heap dump of the configuration prints
//! it. Presented tokens are hashed and compared in constant time (both sides
//! hashed, so neither the content nor the length of the stored token leaks
//! through timing).
//!
//! Strength checks (enforced outside development mode by
//! [`crate::ServerConfig::validate`]): at least [`MIN_TOKEN_LEN`] bytes,
//! an empirical entropy estimate of at least [`MIN_TOKEN_BITS`] bits
//! (length × Shannon entropy of the byte histogram: a typo guard, not a
//! proof of randomness), and not one of the placeholders that the samples
//! in `deploy/` ship with.

/// Shortest token accepted outside development mode (bytes).
pub const MIN_TOKEN_LEN: usize = 16;

/// Smallest entropy estimate accepted outside development mode (bits).
pub const MIN_TOKEN_BITS: f64 = 48.0;

/// Substrings of the placeholder tokens in `deploy/` (case-insensitive).
const PLACEHOLDERS: [&str; 4] = ["change-me", "changeme", "replace_me", "replace-me"];

/// SHA-256 of `bytes` (ring).
pub(crate) fn sha256(bytes: &[u8]) -> [u8; 32] {
    let d = ring::digest::digest(&ring::digest::SHA256, bytes);
    let mut out = [0u8; 32];
    out.copy_from_slice(d.as_ref());
    out
}

/// Constant-time comparison of a presented token with a stored hash.
pub(crate) fn ct_eq_hash(stored_hash: &[u8; 32], presented: &str) -> bool {
    let h = sha256(presented.as_bytes());
    let mut diff = 0u8;
    for (a, b) in stored_hash.iter().zip(h.iter()) {
        diff |= a ^ b;
    }
    std::hint::black_box(diff) == 0
}

/// Length × Shannon entropy of the byte histogram, in bits.
fn entropy_bits(s: &str) -> f64 {
    let b = s.as_bytes();
    if b.is_empty() {
        return 0.0;
    }
    let mut counts = [0u32; 256];
    for &c in b {
        counts[usize::from(c)] += 1;
    }
    let n = b.len() as f64;
    let h: f64 = counts
        .iter()
        .filter(|&&c| c > 0)
        .map(|&c| {
            let p = f64::from(c) / n;
            -p * p.log2()
        })
        .sum();
    h * n
}

/// A tenant's token: its hash and strength, never the secret.
#[derive(Clone, PartialEq, Eq)]
pub struct Token {
    hash: [u8; 32],
    weakness: Option<String>,
}

impl Token {
    /// Hashes `secret` and records why it is weak, if it is.
    pub fn new(secret: &str) -> Token {
        let lower = secret.to_ascii_lowercase();
        let weakness = if secret.is_empty() {
            Some("the token is empty".to_string())
        } else if PLACEHOLDERS.iter().any(|p| lower.contains(p)) {
            Some("the token is a placeholder from the samples".to_string())
        } else if secret.len() < MIN_TOKEN_LEN {
            Some(format!(
                "the token is {} bytes, at least {MIN_TOKEN_LEN} are required",
                secret.len()
            ))
        } else if entropy_bits(secret) < MIN_TOKEN_BITS {
            Some(format!(
                "the token has about {:.0} bits of entropy, at least {MIN_TOKEN_BITS:.0} are required",
                entropy_bits(secret)
            ))
        } else {
            None
        };
        Token {
            hash: sha256(secret.as_bytes()),
            weakness,
        }
    }

    /// Why this token is too weak outside development mode, if it is.
    pub fn weakness(&self) -> Option<&str> {
        self.weakness.as_deref()
    }

    /// Whether `presented` is this token (constant time).
    pub fn matches(&self, presented: &str) -> bool {
        ct_eq_hash(&self.hash, presented)
    }
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("<redacted>")
    }
}

impl From<&str> for Token {
    fn from(s: &str) -> Token {
        Token::new(s)
    }
}

impl From<String> for Token {
    fn from(s: String) -> Token {
        Token::new(&s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weak_tokens_are_named_and_strong_ones_pass() {
        assert!(Token::new("").weakness().unwrap().contains("empty"));
        assert!(Token::new("change-me")
            .weakness()
            .unwrap()
            .contains("placeholder"));
        assert!(Token::new("REPLACE_ME-public-tenant-token")
            .weakness()
            .unwrap()
            .contains("placeholder"));
        assert!(Token::new("s3cret").weakness().unwrap().contains("6 bytes"));
        assert!(Token::new("aaaaaaaaaaaaaaaaaaaaaaaaaaaaaa")
            .weakness()
            .unwrap()
            .contains("entropy"));
        // `openssl rand -hex 32` and `openssl rand -base64 18`.
        assert_eq!(
            Token::new("9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08")
                .weakness(),
            None
        );
        assert_eq!(Token::new("q3Zr8v+Kx1LmPa0TbYw7nE2c").weakness(), None);
    }

    #[test]
    fn only_the_hash_is_kept_and_compared() {
        let t = Token::new("q3Zr8v+Kx1LmPa0TbYw7nE2c");
        assert!(t.matches("q3Zr8v+Kx1LmPa0TbYw7nE2c"));
        assert!(!t.matches("q3Zr8v+Kx1LmPa0TbYw7nE2d"));
        assert!(!t.matches(""));
        assert_eq!(format!("{t:?}"), "<redacted>");
    }
}
