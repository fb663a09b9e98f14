//! The viewer's controls, driven through a real window under Xvfb with
//! synthetic input from `xdotool` (XTEST: real key presses, mouse drags and
//! wheel clicks, as a person's): each control must move the camera as
//! specified, read from the viewer's own per-frame state (`--state`).
//! Needs Xvfb, xdotool and a Vulkan/GL adapter (lavapipe); `.ci/run`
//! installs them, and the test fails, not skips, when one is missing.

mod common;

use common::{start_xvfb, which, xdg_runtime, Killed};
use serde_json::Value;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_planet-view");

/// `name` on the `PATH`; panics when it is not installed.
fn require(name: &str) -> PathBuf {
    which(name).unwrap_or_else(|| panic!("{name} is not installed (apt-get install xvfb xdotool)"))
}

struct Viewer {
    display: u32,
    state: PathBuf,
    window: String,
}

impl Viewer {
    fn xdotool(&self, args: &[&str]) -> String {
        let o = Command::new("xdotool")
            .args(args)
            .env("DISPLAY", format!(":{}", self.display))
            .output()
            .expect("run xdotool");
        assert!(
            o.status.success(),
            "xdotool {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8_lossy(&o.stdout).trim().to_string()
    }

    fn last(&self) -> Value {
        let text = std::fs::read_to_string(&self.state).unwrap_or_default();
        text.lines()
            .rev()
            .find_map(|l| serde_json::from_str(l).ok())
            .unwrap_or(Value::Null)
    }

    /// Wait until the state satisfies `ok` (frames keep coming); returns it.
    fn until(&self, what: &str, ok: impl Fn(&Value) -> bool) -> Value {
        let t0 = Instant::now();
        loop {
            let v = self.last();
            if !v.is_null() && ok(&v) {
                return v;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(60),
                "{what}: last state {v}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The state after at least `n` more frames.
    fn after_frames(&self, n: u64) -> Value {
        let f0 = self.last()["frame"].as_u64().unwrap_or(0);
        self.until("frames", |v| v["frame"].as_u64().unwrap_or(0) >= f0 + n)
    }

    /// Hold `key` for `secs` seconds (real key press and release).
    fn hold(&self, key: &str, secs: f64) -> (Value, Value) {
        let a = self.after_frames(2);
        self.xdotool(&["keydown", key]);
        std::thread::sleep(Duration::from_secs_f64(secs));
        self.xdotool(&["keyup", key]);
        (a, self.after_frames(3))
    }

    fn press(&self, key: &str) -> (Value, Value) {
        let a = self.after_frames(2);
        self.xdotool(&["key", key]);
        (a, self.after_frames(3))
    }
}

fn f(v: &Value, k: &str) -> f64 {
    v[k].as_f64().unwrap_or_else(|| panic!("{k} in {v}"))
}

#[test]
fn every_control_moves_the_camera_as_specified() {
    require("xdotool");
    let (_x, display) =
        start_xvfb(&require("Xvfb"), 500, "1024x768x24").expect("Xvfb did not start");
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("small.planetdb");
    let mut opts = planet_preprocess::default_procedural_options();
    opts.levels = 2;
    opts.seed = 3;
    planet_preprocess::build_procedural(&opts, &db).expect("build the test planet");
    let state = dir.path().join("state.jsonl");
    let xdg = xdg_runtime(dir.path());
    let child = Command::new(BIN)
        .arg("--db")
        .arg(&db)
        .args(["--goto", "10,20,50000", "--width", "640", "--height", "480"])
        .arg("--state")
        .arg(&state)
        .env("DISPLAY", format!(":{display}"))
        .env_remove("WAYLAND_DISPLAY")
        .env("XDG_RUNTIME_DIR", &xdg)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start planet-view");
    let mut child = Killed(child);
    let mut v = Viewer {
        display,
        state,
        window: String::new(),
    };
    let s0 = v.until("first frames", |s| s["frame"].as_u64().unwrap_or(0) >= 3);
    assert_eq!(s0["view"], "--goto");
    assert_eq!(s0["mode"], "fly");
    v.window = v.xdotool(&["search", "--sync", "--name", "planet-view"]);
    let wid = v.window.lines().next().unwrap_or_default().to_string();
    v.xdotool(&["windowfocus", "--sync", &wid]);
    v.xdotool(&["mousemove", "--window", &wid, "320", "240"]);

    // W flies forward (north at heading 0, 20° down: also lower).
    let (a, b) = v.hold("w", 1.0);
    assert!(f(&b, "lat") > f(&a, "lat") + 0.01, "W: {a} -> {b}");
    assert!(
        f(&b, "alt") < f(&a, "alt"),
        "W dives along the view: {a} -> {b}"
    );
    // D strafes east, S flies back.
    let (a, b) = v.hold("d", 1.0);
    assert!(f(&b, "lon") > f(&a, "lon") + 0.01, "D: {a} -> {b}");
    let (a, b) = v.hold("s", 0.5);
    assert!(f(&b, "lat") < f(&a, "lat"), "S: {a} -> {b}");
    // E climbs, Q descends; the speed scales with the altitude.
    let (a, b) = v.hold("e", 0.5);
    assert!(f(&b, "alt") > f(&a, "alt") * 1.05, "E: {a} -> {b}");
    let (a, b) = v.hold("q", 0.5);
    assert!(f(&b, "alt") < f(&a, "alt") * 0.95, "Q: {a} -> {b}");
    // The wheel: up zooms in (lower), down zooms out.
    let (a, b) = {
        let a = v.after_frames(2);
        v.xdotool(&["click", "--repeat", "3", "--delay", "60", "4"]);
        (a, v.after_frames(3))
    };
    assert!(f(&b, "alt") < f(&a, "alt") * 0.9, "wheel up: {a} -> {b}");
    let (a, b) = {
        let a = v.after_frames(2);
        v.xdotool(&["click", "--repeat", "3", "--delay", "60", "5"]);
        (a, v.after_frames(3))
    };
    assert!(f(&b, "alt") > f(&a, "alt") * 1.1, "wheel down: {a} -> {b}");
    // The wheel zooms towards the point under the cursor: on the left of
    // the view (heading north, looking down), the eye moves west; the
    // state names that point on the ground.
    v.xdotool(&["mousemove", "--window", &wid, "60", "400"]);
    let a = v.until("a ground point under the cursor", |s| {
        s["cursor"].is_array()
    });
    v.xdotool(&["click", "--repeat", "3", "--delay", "60", "4"]);
    let b = v.after_frames(3);
    assert!(
        f(&b, "lon") < f(&a, "lon") - 1e-4,
        "wheel at the left: {a} -> {b}"
    );
    assert!(f(&b, "alt") < f(&a, "alt"), "wheel at the left: {a} -> {b}");
    v.xdotool(&["mousemove", "--window", &wid, "320", "240"]);
    // Drag to the right turns the view (heading grows), up/down tilts.
    let a = v.after_frames(2);
    v.xdotool(&["mousemove", "--window", &wid, "200", "240"]);
    v.xdotool(&["mousedown", "1"]);
    for x in (220..=440).step_by(20) {
        v.xdotool(&["mousemove", "--window", &wid, &x.to_string(), "200"]);
        std::thread::sleep(Duration::from_millis(30));
    }
    v.xdotool(&["mouseup", "1"]);
    let b = v.after_frames(3);
    assert!(
        f(&b, "heading") > f(&a, "heading") + 10.0,
        "drag: {a} -> {b}"
    );
    assert!(
        f(&b, "pitch") > f(&a, "pitch"),
        "drag up looks up: {a} -> {b}"
    );
    // Tab: fly -> orbit around the point looked at, and back.
    let (a, b) = v.press("Tab");
    assert_eq!(
        (a["mode"].as_str(), b["mode"].as_str()),
        (Some("fly"), Some("orbit"))
    );
    let (_, b2) = v.press("Tab");
    assert_eq!(b2["mode"], "fly");
    // G: the next view (orbit of the whole planet), then back to --goto.
    let (_, b) = v.press("g");
    assert_eq!(
        (b["view"].as_str(), b["mode"].as_str()),
        (Some("orbit"), Some("orbit"))
    );
    assert!(f(&b, "alt") > 1e6, "G orbit: {b}");
    // In orbit: the arrows move the target, the wheel the range.
    let (a, b) = v.hold("Up", 0.5);
    assert!(
        f(&b, "target_lat") != f(&a, "target_lat") || f(&b, "target_lon") != f(&a, "target_lon"),
        "orbit Up: {a} -> {b}"
    );
    let (_, b) = v.press("g");
    assert_eq!(b["view"], "--goto");
    assert!(
        (f(&b, "lat") - 10.0).abs() < 1e-6 && (f(&b, "alt") - 50_000.0).abs() < 1e-3,
        "{b}"
    );
    // H hides and shows the HUD.
    let (a, b) = v.press("h");
    assert_eq!(
        (a["hud"].as_bool(), b["hud"].as_bool()),
        (Some(true), Some(false))
    );
    let (_, b) = v.press("h");
    assert_eq!(b["hud"], true);
    // A resized window renders at its new size.
    v.xdotool(&["windowsize", &wid, "800", "500"]);
    v.until("resize", |s| s["width"] == 800 && s["height"] == 500);
    // Esc quits cleanly.
    v.xdotool(&["key", "Escape"]);
    let t0 = Instant::now();
    let status = loop {
        if let Ok(Some(s)) = child.0.try_wait() {
            break s;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "Esc did not quit");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "planet-view exited with {status}");
}
