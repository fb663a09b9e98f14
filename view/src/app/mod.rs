//! The viewer application (binary-only modules): data source setup, the
//! client-to-renderer scene, the camera controller, the window, the
//! headless trajectory renderer and its reference / image error.

pub mod camera;
pub mod connect;
pub mod hud;
pub mod reference;
pub mod render_cmd;
pub mod scene;
pub mod snapshot;
pub mod window;
