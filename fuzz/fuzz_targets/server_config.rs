//! The server's TOML configuration: parsing and validation
//! (`ServerConfig::from_toml_str`) must return `Ok` or a `ConfigError`, never
//! panic, whatever the text. Relative paths resolve under a directory that
//! does not exist, so only absolute paths can name real files.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        check(text);
    }
});

/// The same logic as `server/tests/fuzz_regressions.rs::check_server_config`.
fn check(text: &str) {
    let base = std::path::Path::new("/nonexistent/planet-fuzz");
    match planet_server::ServerConfig::from_toml_str(text, base) {
        Ok(cfg) => {
            // A config that parsed is valid, and stays valid.
            cfg.validate()
                .expect("from_toml_str returned an invalid config");
            let _ = cfg.max_tenant_in_flight();
            // Debug output (what logs would show) redacts every token.
            let dbg = format!("{cfg:?}");
            // Tokens are kept as hashes: find each tenant's secret among
            // the quoted strings of the input, and check Debug never shows it.
            let quoted: Vec<&str> = text.split('"').skip(1).step_by(2).collect();
            for t in &cfg.tenants {
                assert!(dbg.contains("<redacted>"));
                for secret in quoted.iter().filter(|q| t.token.matches(q)) {
                    let unique = secret.len() >= 24
                        && !cfg.tenants.iter().any(|o| o.name.contains(secret))
                        && !cfg.databases.iter().any(|d| {
                            d.name.contains(secret) || d.path.to_string_lossy().contains(secret)
                        });
                    assert!(!unique || !dbg.contains(secret), "token in Debug output");
                }
            }
        }
        Err(e) => {
            let _ = e.to_string();
        }
    }
}
