//! LOD sample subsets inside a block, and the data copies of split and merge.
//!
//! Implements thesis §3.2 and §3.4.1 (Generic paper §4; docs/REFERENCES.md) with
//! `subDepth = 1`: every block has two LODs. LOD 1 (the first) is a subset of
//! LOD 0 (the full grid); the block's LOD 1 is exactly its parent's samples
//! over its quadrant, so it is never stored (Thesis §3.2.2), and the one
//! stored record of a block carries only the samples LOD 0 adds, interleaved
//! between the existing ones.
//!
//! - **Elevation** grids are odd: `(W+1)²` samples, the last row and column
//!   shared with the next block (thesis §3.2, §4.2.1). LOD 1 is the samples
//!   with even `i` and even `j`, `(W/2+1)²` of them, point-sampled
//!   (Thesis §3.2, docs/REFERENCES.md). The block width `W` must be even.
//! - **Colour** grids are even: `W²` texels with centres at `(i + ½)/W`. LOD 1
//!   is a separate `(W/2)²` grid, the floor of the mean of each 2×2 cell
//!   (filtered, not point-sampled: thesis §4.4.4), and LOD 0 is reconstructed
//!   from it losslessly (see [`crate::codec`]).
//!
//! Grids are stored row-major with `i` along the face's `u` axis (columns) and
//! `j` along `v` (rows): index `j·side + i`.

/// RGB8 colour sample.
pub type Rgb = [u8; 3];

/// Side length of an elevation grid of width `w` (`w + 1`).
#[inline]
pub fn elevation_side(w: usize) -> usize {
    w + 1
}

/// Whether elevation sample `(i, j)` belongs to LOD 1 (the parent's samples).
#[inline]
pub fn is_first_lod(i: usize, j: usize) -> bool {
    i.is_multiple_of(2) && j.is_multiple_of(2)
}

/// Number of samples a block's LOD 0 record adds to its LOD 1.
pub fn elevation_new_samples(w: usize) -> usize {
    let side = w + 1;
    let half = w / 2 + 1;
    side * side - half * half
}

/// The largest tree-level difference `x` between neighbouring blocks that
/// edge strips can stitch: the largest `x` with `w` divisible by `2^(x+1)`
/// (Thesis §4.3.3; the table in docs/REFERENCES.md).
pub fn max_level_difference(w: usize) -> u32 {
    if w == 0 {
        return 0;
    }
    w.trailing_zeros().saturating_sub(1)
}

/// Copy the child `k`'s quadrant of a parent's full elevation grid into the
/// child's LOD 1 positions (split, thesis §3.4.1). `child` must have
/// `(w+1)²` samples; its other positions are left untouched.
pub fn split_elevation(parent: &[i16], w: usize, k: usize, child: &mut [i16]) {
    let side = w + 1;
    let (ox, oy) = ((k & 1) * w / 2, (k >> 1) * w / 2);
    for j in 0..=w / 2 {
        for i in 0..=w / 2 {
            child[2 * j * side + 2 * i] = parent[(oy + j) * side + ox + i];
        }
    }
}

/// Copy a child's LOD 1 samples back into the parent's full grid (merge, or
/// the preprocessor's bottom-up gather). Shared edges are written by both
/// neighbouring children with equal values.
pub fn merge_elevation(child: &[i16], w: usize, k: usize, parent: &mut [i16]) {
    let side = w + 1;
    let (ox, oy) = ((k & 1) * w / 2, (k >> 1) * w / 2);
    for j in 0..=w / 2 {
        for i in 0..=w / 2 {
            parent[(oy + j) * side + ox + i] = child[2 * j * side + 2 * i];
        }
    }
}

/// Extract the LOD 1 samples `(W/2+1)²` of a full elevation grid.
pub fn elevation_first_lod(full: &[i16], w: usize) -> Vec<i16> {
    let side = w + 1;
    let mut out = Vec::with_capacity((w / 2 + 1) * (w / 2 + 1));
    for j in (0..=w).step_by(2) {
        for i in (0..=w).step_by(2) {
            out.push(full[j * side + i]);
        }
    }
    out
}

/// Place a compact LOD 1 array `(W/2+1)²` into the even positions of a full
/// `(W+1)²` grid.
pub fn elevation_place_first_lod(lod1: &[i16], w: usize, full: &mut [i16]) {
    let side = w + 1;
    let half = w / 2 + 1;
    for j in 0..half {
        for i in 0..half {
            full[2 * j * side + 2 * i] = lod1[j * half + i];
        }
    }
}

/// The filtered LOD 1 of a full colour grid: floor of each 2×2 cell's mean.
pub fn colour_filter(full: &[Rgb], w: usize) -> Vec<Rgb> {
    let h = w / 2;
    let mut out = vec![[0u8; 3]; h * h];
    for j in 0..h {
        for i in 0..h {
            let a = full[2 * j * w + 2 * i];
            let b = full[2 * j * w + 2 * i + 1];
            let c = full[(2 * j + 1) * w + 2 * i];
            let d = full[(2 * j + 1) * w + 2 * i + 1];
            for ch in 0..3 {
                let s = a[ch] as u16 + b[ch] as u16 + c[ch] as u16 + d[ch] as u16;
                out[j * h + i][ch] = (s / 4) as u8;
            }
        }
    }
    out
}

/// Geometric error of rendering a full elevation grid at its first LOD
/// (thesis §3.2): max |LOD 0 − bilinear(LOD 1)| in stored units, LOD 1
/// being the even samples interpolated within their 2 × 2 cells. Scaled to
/// metres, it is the elevation record's [`crate::format::ChildRef::error`].
pub fn elevation_lod_error(full: &[i16], w: usize) -> f64 {
    // In quarter units (exact integers): edge middles are |2x − a − b| / 2,
    // cell centres |4x − (sum of 4 corners)| / 4.
    let side = w + 1;
    let row = |j: usize| &full[j * side..(j + 1) * side];
    let mut e4 = 0i32;
    for j in 0..side {
        let r = row(j);
        if j % 2 == 0 {
            for i in (1..side - 1).step_by(2) {
                let d = 2 * r[i] as i32 - (r[i - 1] as i32 + r[i + 1] as i32);
                e4 = e4.max(2 * d.abs());
            }
        } else {
            let (up, down) = (row(j - 1), row(j + 1));
            for i in (0..side).step_by(2) {
                let d = 2 * r[i] as i32 - (up[i] as i32 + down[i] as i32);
                e4 = e4.max(2 * d.abs());
            }
            for i in (1..side - 1).step_by(2) {
                let d = 4 * r[i] as i32
                    - (up[i - 1] as i32
                        + up[i + 1] as i32
                        + down[i - 1] as i32
                        + down[i + 1] as i32);
                e4 = e4.max(d.abs());
            }
        }
    }
    e4 as f64 / 4.0
}

/// Colour error of rendering a block at its filtered first LOD (thesis
/// §4.4.4, [`colour_filter`]): max channel difference between each texel and
/// its 2×2 cell's LOD 1 value, the colour record's
/// [`crate::format::ChildRef::error`].
pub fn colour_lod_error(full: &[Rgb], lod1: &[Rgb], w: usize) -> f64 {
    let h = w / 2;
    let mut e = 0u8;
    for j in 0..w {
        for i in 0..w {
            let m = lod1[(j / 2) * h + i / 2];
            let t = full[j * w + i];
            for ch in 0..3 {
                e = e.max(t[ch].abs_diff(m[ch]));
            }
        }
    }
    e as f64
}

/// The child `k`'s LOD 1 `(W/2)²` grid: its quadrant of the parent's full
/// `W²` colour grid (split).
pub fn split_colour(parent: &[Rgb], w: usize, k: usize) -> Vec<Rgb> {
    let h = w / 2;
    let (ox, oy) = ((k & 1) * h, (k >> 1) * h);
    let mut out = Vec::with_capacity(h * h);
    for j in 0..h {
        out.extend_from_slice(&parent[(oy + j) * w + ox..(oy + j) * w + ox + h]);
    }
    out
}

/// Write a child's LOD 1 `(W/2)²` grid into its quadrant of the parent's full
/// colour grid (merge, or the preprocessor's bottom-up gather).
pub fn merge_colour(child_lod1: &[Rgb], w: usize, k: usize, parent: &mut [Rgb]) {
    let h = w / 2;
    let (ox, oy) = ((k & 1) * h, (k >> 1) * h);
    for j in 0..h {
        parent[(oy + j) * w + ox..(oy + j) * w + ox + h]
            .copy_from_slice(&child_lod1[j * h..(j + 1) * h]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_difference_table() {
        // Thesis §4.3.3, the table in docs/REFERENCES.md
        for (w, x) in [
            (12, 1),
            (52, 1),
            (64, 5),
            (84, 1),
            (88, 2),
            (104, 2),
            (168, 2),
            (180, 1),
            (256, 7),
        ] {
            assert_eq!(max_level_difference(w), x, "w = {w}");
        }
    }

    #[test]
    fn split_then_merge_restores_parent() {
        let w = 8;
        let side = w + 1;
        let parent: Vec<i16> = (0..side * side).map(|v| v as i16 * 3 - 40).collect();
        let mut rebuilt = vec![0i16; side * side];
        for k in 0..4 {
            let mut child = vec![i16::MIN; side * side];
            split_elevation(&parent, w, k, &mut child);
            // Exactly LOD 1 positions are written.
            for j in 0..side {
                for i in 0..side {
                    assert_eq!(child[j * side + i] != i16::MIN, is_first_lod(i, j));
                }
            }
            let lod1 = elevation_first_lod(&child, w);
            let mut again = vec![i16::MIN; side * side];
            elevation_place_first_lod(&lod1, w, &mut again);
            assert_eq!(again, child);
            merge_elevation(&child, w, k, &mut rebuilt);
        }
        assert_eq!(rebuilt, parent);
        assert_eq!(elevation_new_samples(64), 65 * 65 - 33 * 33);
    }

    #[test]
    fn colour_split_merge() {
        let w = 8;
        let parent: Vec<Rgb> = (0..w * w)
            .map(|v| [v as u8, (v * 7) as u8, (255 - v) as u8])
            .collect();
        let mut rebuilt = vec![[0u8; 3]; w * w];
        for k in 0..4 {
            merge_colour(&split_colour(&parent, w, k), w, k, &mut rebuilt);
        }
        assert_eq!(rebuilt, parent);
        let f = colour_filter(&[[0, 1, 255], [1, 1, 255], [2, 1, 255], [3, 2, 254]], 2);
        assert_eq!(f, vec![[1, 1, 254]]);
    }
}
