//! The output file is replaced whole or not at all: concurrent builds to
//! one output, a build killed midway, and a build that fills the disk.

use planet_preprocess::db::{verify, Sampler};
use planet_preprocess::{build_procedural, ProceduralOptions};
use std::collections::HashMap;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// The legacy codecs: files of known, larger sizes (the disk-full test
/// needs 3 levels not to fit in 4 MiB; the default codecs make 1.5 MB).
fn opts(seed: u64, levels: u8) -> ProceduralOptions {
    ProceduralOptions {
        seed,
        levels,
        quiet: true,
        codecs: planet_preprocess::CodecOptions {
            elevation: planet_preprocess::ElevationChoice::Legacy,
            colour: planet_preprocess::ColourQuality::LosslessLegacy,
        },
        ..planet_preprocess::default_procedural_options()
    }
}

fn temporaries(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".tmp"))
        .collect()
}

/// Every elevation block's decoded grid.
fn blocks(db: &Path) -> HashMap<planet_core::BlockId, Vec<i16>> {
    let mut m = HashMap::new();
    Sampler::open(db)
        .unwrap()
        .for_each_elevation_block(|b, g| {
            m.insert(b, g.to_vec());
        })
        .unwrap();
    m
}

#[test]
fn concurrent_builds_to_one_output_do_not_clobber_each_other() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("same.db");
    // References built apart.
    let (ra, rb) = (dir.path().join("a.db"), dir.path().join("b.db"));
    build_procedural(&opts(1, 3), &ra).unwrap();
    build_procedural(&opts(2, 3), &rb).unwrap();
    // Record order varies between parallel builds: compare decoded blocks.
    let (a, b) = (blocks(&ra), blocks(&rb));
    assert_ne!(a, b);
    std::thread::scope(|s| {
        let h1 = s.spawn(|| build_procedural(&opts(1, 3), &out));
        let h2 = s.spawn(|| build_procedural(&opts(2, 3), &out));
        h1.join().unwrap().unwrap();
        h2.join().unwrap().unwrap();
    });
    verify(&out).unwrap();
    let got = blocks(&out);
    assert!(got == a || got == b, "the output is neither build whole");
    assert!(
        temporaries(dir.path()).is_empty(),
        "{:?}",
        temporaries(dir.path())
    );
}

#[test]
fn a_killed_build_leaves_the_old_output_intact() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("planet.db");
    build_procedural(&opts(1, 2), &out).unwrap();
    let before = std::fs::read(&out).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_planet-build"))
        .args([
            "build",
            "--procedural",
            "--levels",
            "7",
            "--quiet",
            "--threads",
            "1",
            "--out",
        ])
        .arg(&out)
        .spawn()
        .unwrap();
    // Kill it once its temporary holds some records.
    let t0 = Instant::now();
    loop {
        let big = std::fs::read_dir(dir.path())
            .unwrap()
            .filter_map(|e| e.ok())
            .any(|e| {
                e.file_name().to_string_lossy().ends_with(".tmp")
                    && e.metadata().map(|m| m.len() > 256 << 10).unwrap_or(false)
            });
        if big {
            break;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the build ended before it could be killed"
        );
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "no temporary appeared"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap();
    let status = child.wait().unwrap();
    assert!(!status.success());
    assert_eq!(std::fs::read(&out).unwrap(), before, "old output changed");
    verify(&out).unwrap();
}

/// Unmounts on drop.
struct Mount(std::path::PathBuf);
impl Drop for Mount {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

#[test]
fn a_full_disk_is_named_and_leaves_no_temporary() {
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("small");
    std::fs::create_dir(&mnt).unwrap();
    // A 4 MiB tmpfs (needs the right to mount, as root in CI's container).
    let ok = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=4m", "tmpfs"])
        .arg(&mnt)
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    if !ok {
        eprintln!("note: cannot mount a tmpfs here (not root?): disk-full test not run");
        return;
    }
    let _guard = Mount(mnt.clone());
    let out = mnt.join("planet.db");
    build_procedural(&opts(1, 1), &out).unwrap();
    let before = std::fs::read(&out).unwrap();
    // 0.75 MB; then 8.8 MB, which does not fit.
    let err = build_procedural(&opts(1, 3), &out).expect_err("3 levels do not fit in 4 MiB");
    let msg = format!("{err:#}");
    assert!(msg.contains("disk full"), "{msg}");
    assert!(temporaries(&mnt).is_empty(), "{:?}", temporaries(&mnt));
    assert_eq!(std::fs::read(&out).unwrap(), before);
}
