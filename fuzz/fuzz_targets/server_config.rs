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
            for t in &cfg.tenants {
                assert!(dbg.contains("<redacted>"));
                let unique = t.token.len() >= 24
                    && !cfg.tenants.iter().any(|o| o.name.contains(&t.token))
                    && !cfg.databases.iter().any(|d| {
                        d.name.contains(&t.token) || d.path.to_string_lossy().contains(&t.token)
                    });
                assert!(!unique || !dbg.contains(&t.token), "token in Debug output");
            }
        }
        Err(e) => {
            let _ = e.to_string();
        }
    }
}
