//! Replays the `raster_readers` fuzz corpus and regressions
//! (fuzz/fuzz_targets/raster_readers.rs) without cargo-fuzz: every file is
//! probed as a raster; errors are fine, panics are not.

use std::path::PathBuf;

#[test]
fn raster_reader_corpus_replays_without_panic() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let dir = tempfile::tempdir().unwrap();
    let mut n = 0;
    let mut opened = 0;
    for sub in ["corpus/raster_readers", "regressions/raster_readers"] {
        let Ok(rd) = std::fs::read_dir(root.join(sub)) else {
            continue;
        };
        for e in rd.flatten() {
            let p = dir.path().join("input.tif");
            std::fs::copy(e.path(), &p).unwrap();
            if planet_preprocess::geotiff::probe(&p).is_ok() {
                opened += 1;
            }
            n += 1;
        }
    }
    assert!(n >= 5, "the corpus holds {n} files");
    assert!(opened >= 5, "only {opened} of the seeds open");
}
