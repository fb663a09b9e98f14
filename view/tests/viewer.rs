//! End-to-end tests of the `planet-view` binary: the headless `render`
//! command (CSV, image error against the complete database) and the
//! interactive window under Xvfb (screenshot). Both stream from an
//! in-process server over real QUIC. They print a note and pass when no
//! graphics adapter (or no Xvfb) exists, and fail instead under `PLANET_CI=1`
//! (`common::skip_or_fail`).

mod common;

use common::{start_xvfb, which, xdg_runtime};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

const BIN: &str = env!("CARGO_BIN_EXE_planet-view");

/// A small procedural planet (3 levels, colour), built once per test.
fn small_db(dir: &Path, name: &str) -> PathBuf {
    let path = dir.join(name);
    let mut opts = planet_preprocess::default_procedural_options();
    opts.levels = 3;
    opts.seed = 7;
    opts.threads = Some(2);
    let t0 = Instant::now();
    planet_preprocess::build_procedural(&opts, &path).expect("build the test database");
    eprintln!("test database built in {:.1} s", t0.elapsed().as_secs_f64());
    path
}

fn no_adapter(stderr: &str) -> bool {
    stderr.contains("no graphics adapter") || stderr.contains("NoAdapter")
}

struct Row {
    written: bool,
    bytes: u64,
    rmse: f64,
    psnr: f64,
    mismatch: f64,
}

fn read_csv(path: &Path) -> Vec<Row> {
    let text = std::fs::read_to_string(path).expect("frames.csv");
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| {
        head.iter()
            .position(|h| *h == name)
            .unwrap_or_else(|| panic!("column {name}"))
    };
    let (w, b, r, p, m) = (
        col("written"),
        col("bytes_received"),
        col("depth_rmse_m"),
        col("psnr_db"),
        col("coverage_mismatch_px"),
    );
    for c in [
        "frame",
        "time_s",
        "in_flight",
        "cancelled",
        "blocks",
        "triangles",
        "quality_factor",
        "max_sse_px",
        "mean_sse_px",
    ] {
        col(c);
    }
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            assert_eq!(f.len(), head.len(), "row {l}");
            let num = |k: usize| f[k].parse::<f64>().unwrap_or(f64::NAN);
            Row {
                written: f[w] == "1",
                bytes: f[b].parse().unwrap(),
                rmse: num(r),
                psnr: num(p),
                mismatch: num(m),
            }
        })
        .collect()
}

/// Run `planet-view render` over `db` along `keyframes` (lines of `t lat
/// lon alt heading pitch`) at 4 fps and 160×120, with `args` added; returns
/// the output directory and the process's output.
fn render_flight(
    dir: &Path,
    db: &Path,
    keyframes: &str,
    args: &[&str],
) -> (PathBuf, std::process::Output) {
    let traj = dir.join("flight.txt");
    std::fs::write(&traj, format!("# t lat lon alt heading pitch\n{keyframes}")).unwrap();
    let out = dir.join("out");
    let o = Command::new(BIN)
        .args(["render", "--trajectory"])
        .arg(&traj)
        .arg("--db")
        .arg(db)
        .arg("--out")
        .arg(&out)
        .args(["--fps", "4", "--width", "160", "--height", "120"])
        .args(args)
        .env("XDG_RUNTIME_DIR", xdg_runtime(dir))
        .output()
        .expect("run planet-view render");
    (out, o)
}

#[test]
fn render_command_writes_frames_and_the_error_falls_as_the_stream_converges() {
    let dir = tempfile::tempdir().unwrap();
    let db = small_db(dir.path(), "small.planetdb");
    // Hold still 350 km above the procedural planet, looking 50° down.
    let (out, o) = render_flight(
        dir.path(),
        &db,
        "0 25 15 350000 30 -50\n5 25 15 350000 30 -50\n",
        &["--every", "4", "--reference"],
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    let stdout = String::from_utf8_lossy(&o.stdout);
    eprintln!("{stdout}\n{stderr}");
    if !o.status.success() && no_adapter(&stderr) {
        common::skip_or_fail("no graphics adapter");
        return;
    }
    assert!(o.status.success(), "render failed");
    assert!(stdout.contains("image error"), "summary printed");
    let rows = read_csv(&out.join("frames.csv"));
    assert_eq!(rows.len(), 21, "5 s at 4 fps");
    let written: Vec<&Row> = rows.iter().filter(|r| r.written).collect();
    assert_eq!(written.len(), 6);
    for (k, r) in written.iter().enumerate() {
        assert!(
            r.rmse.is_finite() && r.psnr.is_finite() && r.mismatch.is_finite(),
            "row {k}"
        );
        let png = out.join(format!("frame_{:05}.png", k * 4));
        assert!(png.exists(), "{}", png.display());
    }
    assert!(rows.last().unwrap().bytes > rows[0].bytes, "data arrived");
    let (first, last) = (written[0], written[written.len() - 1]);
    eprintln!(
        "PSNR {:.2} -> {:.2} dB, depth RMSE {:.1} -> {:.1} m, mismatch {} -> {}",
        first.psnr, last.psnr, first.rmse, last.rmse, first.mismatch, last.mismatch
    );
    assert!(
        last.psnr > first.psnr + 1.0,
        "PSNR rises as the stream converges"
    );
    // The default client refines elevation only where its screen-space
    // error exceeds 1 px: from 350 km the first blocks may already be
    // within it (the depth error then stays), never worse.
    assert!(
        last.rmse <= first.rmse,
        "depth error does not grow as the stream converges"
    );
}

/// `render --time` times every frame (client, scene, drawing) into the CSV
/// and timing.json; with `--target-fps` the controller, fed those costs,
/// never raises QF above its initial value (anti-windup), and without
/// `--time` the flag is refused by name.
#[test]
fn render_time_records_every_frame_and_the_controller_stays_under_its_ceiling() {
    let dir = tempfile::tempdir().unwrap();
    let db = small_db(dir.path(), "small.planetdb");
    let keyframes = "0 25 15 350000 30 -50\n3 25 25 20000 30 -20\n";
    let run = |extra: &[&str]| render_flight(dir.path(), &db, keyframes, extra);
    let (_, refused) = run(&["--every", "100", "--target-fps", "4"]);
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("--time"),
        "the error names --time"
    );
    let (out, o) = run(&["--every", "100", "--time", "--target-fps", "4"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    eprintln!("{}\n{stderr}", String::from_utf8_lossy(&o.stdout));
    if !o.status.success() && no_adapter(&stderr) {
        common::skip_or_fail("no graphics adapter");
        return;
    }
    assert!(o.status.success(), "render --time failed");
    let text = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| head.iter().position(|h| *h == name).unwrap();
    let (qf, parts) = (
        col("quality_factor"),
        ["client_ms", "scene_ms", "encode_ms", "draw_ms"].map(col),
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 13, "3 s at 4 fps");
    for r in &rows {
        for &k in &parts {
            let ms: f64 = r[k].parse().expect("a time in every row");
            assert!(ms.is_finite() && ms >= 0.0, "{}: {ms}", head[k]);
        }
        let q: f64 = r[qf].parse().unwrap();
        assert!(q <= 1e4, "QF {q} above its initial value");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("timing.json")).unwrap()).unwrap();
    assert_eq!(json["frames"], 13);
    let frame = &json["frame_ms"];
    assert!(frame["median"].as_f64().unwrap() <= frame["max"].as_f64().unwrap());
    assert!(json["frames_over_budget"].as_u64().unwrap() <= 13);
}

fn read_png(path: &Path) -> (u32, u32, Vec<u8>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgba);
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

#[test]
fn window_under_xvfb_shows_the_planet() {
    let Some(xvfb) = which("Xvfb") else {
        common::skip_or_fail("Xvfb is not installed");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // --local builds the built-in planet into an empty cache on first use,
    // and uses it as it is the second time.
    let cache = dir.path().join("cache");
    let Some((_x, n)) = start_xvfb(&xvfb, 90, "800x600x24") else {
        common::skip_or_fail("Xvfb did not start");
        return;
    };
    let shot = dir.path().join("shot.png");
    let run = || {
        let t0 = Instant::now();
        let o = Command::new(BIN)
            .args([
                "--local",
                "--width",
                "640",
                "--height",
                "480",
                "--screenshot",
            ])
            .arg(&shot)
            .args(["--exit-after-frames", "120"])
            .env("DISPLAY", format!(":{n}"))
            .env_remove("WAYLAND_DISPLAY")
            .env("PLANET_CACHE", &cache)
            .env("XDG_RUNTIME_DIR", xdg_runtime(dir.path()))
            .output()
            .expect("run planet-view");
        let stderr = String::from_utf8_lossy(&o.stderr).to_string();
        eprintln!("{stderr}\n(run took {:.1} s)", t0.elapsed().as_secs_f64());
        (o.status.success(), stderr)
    };
    let (ok, stderr) = run();
    if !ok
        && (no_adapter(&stderr)
            || stderr.contains("requesting the device")
            || stderr.contains("creating the surface"))
    {
        common::skip_or_fail("no Vulkan/GL adapter for the window");
        return;
    }
    assert!(ok, "planet-view failed");
    assert!(
        stderr.contains("building the built-in planet"),
        "first use builds the planet"
    );
    let db = planet_core::format::DbFile::open(&cache.join("default.planetdb"))
        .expect("the cached planet opens");
    assert_eq!(
        db.header.elevation.max_level,
        planet_preprocess::builtin::PLACE_LEVEL,
        "the built-in planet is deep where the places are"
    );
    let (ok, stderr) = run();
    assert!(ok, "planet-view failed the second time");
    assert!(
        !stderr.contains("building the built-in planet") && !stderr.contains("rebuilding"),
        "the cached planet is used as it is"
    );
    let (w, h, rgba) = read_png(&shot);
    assert_eq!((w, h), (640, 480));
    let px = |x: u32, y: u32| {
        let k = ((y * w + x) * 4) as usize;
        [rgba[k], rgba[k + 1], rgba[k + 2]]
    };
    // Background: the renderer's clear colour, as in the bottom-right corner.
    let bg = px(w - 1, h - 1);
    let is_bg = |c: [u8; 3]| (0..3).all(|k| (c[k] as i32 - bg[k] as i32).abs() <= 6);
    let centre = px(w / 2, h / 2);
    assert!(!is_bg(centre), "centre pixel {centre:?} is background");
    let planet = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| !is_bg(px(x, y)))
        .count();
    let share = planet as f64 / (w * h) as f64;
    eprintln!("non-background share {share:.2}, centre {centre:?}");
    assert!(share > 0.2, "planet covers {share:.2} of the window");
}
