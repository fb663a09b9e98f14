//! Finds the named places of the default procedural planet: scans a built
//! procedural database on a 0.25° grid and prints the best candidates for a
//! mountain range (highest local relief), a steep coast (deep sea next to
//! high land) and a canyon (a narrow low line inside high ground).
//!
//! `cargo run --release -p planet-preprocess --example find_places -- DB`

use planet_preprocess::db::Sampler;
use std::collections::HashMap;

fn main() -> anyhow::Result<()> {
    let path = std::env::args()
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("usage: find_places DB"))?;
    let s = Sampler::open(std::path::Path::new(&path))?;
    let step = 0.25;
    let (nlat, nlon) = ((140.0 / step) as usize + 1, (360.0 / step) as usize);
    let mut cache = HashMap::new();
    let mut e = vec![0f64; nlat * nlon];
    for j in 0..nlat {
        for i in 0..nlon {
            let (lat, lon) = (-70.0 + j as f64 * step, -180.0 + i as f64 * step);
            e[j * nlon + i] = s.sample_cached(lat, lon, &mut cache)?.metres;
        }
        if cache.len() > 4000 {
            cache.clear();
        }
    }
    let at = |j: usize, i: isize| e[j * nlon + i.rem_euclid(nlon as isize) as usize];
    let r = 2isize; // ±0.5°
    let mut mountain = Vec::new();
    let mut coast = Vec::new();
    let mut canyon = Vec::new();
    for j in r as usize..nlat - r as usize {
        for i in 0..nlon as isize {
            let c = at(j, i);
            let (mut lo, mut hi, mut sum, mut n) = (f64::MAX, f64::MIN, 0.0, 0.0);
            for dj in -r..=r {
                for di in -r..=r {
                    let v = at((j as isize + dj) as usize, i + di);
                    lo = lo.min(v);
                    hi = hi.max(v);
                    sum += v;
                    n += 1.0;
                }
            }
            let (lat, lon) = (-70.0 + j as f64 * step, -180.0 + i as f64 * step);
            if c > 0.0 {
                mountain.push((hi - lo + c, lat, lon, c));
            }
            if c.abs() < 150.0 && lo < -1000.0 && hi > 1000.0 {
                coast.push((hi - lo, lat, lon, c));
            }
            if c > 200.0 {
                canyon.push((sum / n - c, lat, lon, c));
            }
        }
    }
    for (name, mut v) in [("mountain", mountain), ("coast", coast), ("canyon", canyon)] {
        v.sort_by(|a, b| b.0.total_cmp(&a.0));
        println!("{name}:");
        let mut shown: Vec<(f64, f64)> = Vec::new();
        for (score, lat, lon, c) in v {
            if shown
                .iter()
                .any(|(a, b)| (a - lat).abs() < 5.0 && (b - lon).abs() < 5.0)
            {
                continue;
            }
            println!("  score {score:8.0}  lat {lat:7.2} lon {lon:8.2}  elev {c:6.0} m");
            shown.push((lat, lon));
            if shown.len() == 6 {
                break;
            }
        }
    }
    Ok(())
}
