//! The seeded request list: a flight-like size mix over every record of
//! the database.

use std::path::Path;

use anyhow::{anyhow, bail, Result};
use planet_core::format::Tree;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// One request: a record's file range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Req {
    /// File offset.
    pub offset: u64,
    /// Size in bytes.
    pub size: u32,
}

/// What the request list holds.
#[derive(Debug, Clone)]
pub struct RequestList {
    /// The requests, replayed cyclically.
    pub reqs: Vec<Req>,
    /// Records in the database (elevation, colour).
    pub records: (usize, usize),
    /// Mean request size.
    pub mean_size: f64,
    /// Elevation share actually drawn.
    pub elevation_share: f64,
}

/// Every record of `db` and a seeded request list of `len` entries:
/// `elevation_share` elevation records, the rest colour, each tree's level
/// drawn uniformly and the record uniformly within its level.
pub fn request_list(db: &Path, len: usize, seed: u64, elevation_share: f64) -> Result<RequestList> {
    let (_, recs) =
        planet_preprocess::db::scan(db).map_err(|e| anyhow!("scan {}: {e}", db.display()))?;
    // by_level[tree][level] = records
    let mut by_level: [Vec<Vec<Req>>; 2] = [vec![], vec![]];
    for r in &recs {
        let t = match r.tree {
            Tree::Elevation => 0,
            Tree::Colour => 1,
        };
        let l = r.block.level as usize;
        if by_level[t].len() <= l {
            by_level[t].resize(l + 1, vec![]);
        }
        by_level[t][l].push(Req {
            offset: r.offset,
            size: r.size,
        });
    }
    for t in &mut by_level {
        t.retain(|l| !l.is_empty());
    }
    let counts = (
        by_level[0].iter().map(Vec::len).sum::<usize>(),
        by_level[1].iter().map(Vec::len).sum::<usize>(),
    );
    if counts.0 + counts.1 == 0 {
        bail!("{} has no records", db.display());
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut reqs = Vec::with_capacity(len);
    let mut elev = 0usize;
    for _ in 0..len.max(1) {
        let mut t = if rng.random::<f64>() < elevation_share {
            0
        } else {
            1
        };
        if by_level[t].is_empty() {
            t = 1 - t;
        }
        if t == 0 {
            elev += 1;
        }
        let levels = &by_level[t];
        let level = &levels[rng.random_range(0..levels.len())];
        reqs.push(level[rng.random_range(0..level.len())]);
    }
    let mean_size = reqs.iter().map(|r| r.size as f64).sum::<f64>() / reqs.len() as f64;
    let n = reqs.len();
    Ok(RequestList {
        reqs,
        records: counts,
        mean_size,
        elevation_share: elev as f64 / n as f64,
    })
}
