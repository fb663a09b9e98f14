//! Shared by the GPU test files: a headless renderer on whatever adapter
//! wgpu finds (lavapipe in CI), or `None` with a note when there is none;
//! [`skip_or_fail`], through which every skip of these tests goes.

use planet_render::HeadlessRenderer;

/// A `width × height` headless renderer, with `XDG_RUNTIME_DIR` set to a
/// private temporary directory when the environment has none (Mesa warns
/// without one).
pub fn headless(width: u32, height: u32) -> Option<HeadlessRenderer> {
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        let dir = std::env::temp_dir().join("planet-view-xdg");
        let _ = std::fs::create_dir_all(&dir);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let _ = std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o700));
        }
        std::env::set_var("XDG_RUNTIME_DIR", &dir);
    }
    match HeadlessRenderer::new(width, height) {
        Ok(r) => {
            eprintln!("adapter: {}", r.adapter_name);
            Some(r)
        }
        Err(e) => {
            skip_or_fail(&format!("no GPU adapter: {e}"));
            None
        }
    }
}

/// Skips a test that cannot run here; fails in CI
/// ([`planet_testkit::skip_or_fail`]).
#[allow(unused_imports)] // not every test file that shares this module skips
pub use planet_testkit::skip_or_fail;
