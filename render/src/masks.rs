//! Index masks shared by all blocks: one interior mask per LOD plus the edge
//! strip masks that stitch a block to a coarser neighbour (thesis §4.2.2,
//! §4.3.1; Planetary paper §5.1).
//!
//! A block's vertex array is its full `(W+1)²` elevation grid, row-major with
//! `i` along `u` and `j` along `v` (vertex `j·(W+1) + i`). LOD `l` uses the
//! samples on a grid of step `s = 2^l`.
//!
//! The block square is split into five parts:
//!
//! - the **interior** `[s, W−s]²`, a regular grid of step `s`, two triangles
//!   per cell;
//! - four **edge trapezoids**, e.g. for Bottom the polygon `(0,0), (W,0),
//!   (W−s,s), (s,s)`. Their inner side uses every step-`s` vertex (exactly the
//!   interior's boundary vertices), their outer side uses only every
//!   `s·2^d`-th vertex, where `d` is how many definition levels coarser the
//!   neighbour is on that edge: those are exactly the neighbour's vertices, so
//!   the shared edge has no crack and no T-junction. Adjacent trapezoids
//!   share the corner diagonal `(0,0)–(s,s)`.
//!
//! The trapezoids are triangulated by zipping the two chains (a triangle list,
//! counter-clockwise in `(i, j)`, i.e. counter-clockwise seen from outside
//! the planet since each face frame `(u, v, w)` is right-handed).

use planet_core::Edge;

/// A range of indices in [`Masks::indices`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct IndexRange {
    /// First index.
    pub start: u32,
    /// Number of indices (a multiple of 3; may be 0).
    pub count: u32,
}

impl IndexRange {
    /// As a `Range<u32>` for `draw_indexed`.
    pub fn range(&self) -> std::ops::Range<u32> {
        self.start..self.start + self.count
    }
}

/// The masks of one LOD.
#[derive(Debug, Clone)]
pub struct LodMasks {
    /// Sample step of this LOD (`2^lod`).
    pub step: usize,
    /// The interior `[s, W−s]²`.
    pub interior: IndexRange,
    /// `edges[edge][d]`: the trapezoid along `edge` stitched to a neighbour
    /// `2^d` times coarser. `d` runs over `0..=max_diff`.
    pub edges: [Vec<IndexRange>; 4],
}

impl LodMasks {
    /// The largest definition difference this LOD can stitch.
    pub fn max_diff(&self) -> u8 {
        (self.edges[0].len() - 1) as u8
    }
}

/// All masks for a block width, in one index array (u32 indices).
#[derive(Debug, Clone)]
pub struct Masks {
    /// Block width `W` (vertices per side `W + 1`).
    pub w: usize,
    /// All indices; the ranges below point into it.
    pub indices: Vec<u32>,
    /// Per LOD (0 = full grid, 1 = step 2).
    pub lods: Vec<LodMasks>,
}

/// Largest definition difference LOD `lod` can stitch on a block of width `w`:
/// the outer step `2^(lod+d)` must divide `w`.
pub fn max_diff_for(w: usize, lod: u8) -> u8 {
    (w.trailing_zeros() as u8).saturating_sub(lod)
}

impl Masks {
    /// Build the masks for LODs 0 and 1 of a block of width `w` (even, ≥ 4).
    pub fn new(w: usize) -> Masks {
        assert!(
            w >= 4 && w.is_multiple_of(4),
            "block width must be a multiple of 4, got {w}"
        );
        let mut indices = Vec::new();
        let mut lods = Vec::new();
        for lod in 0..2u8 {
            let s = 1usize << lod;
            let start = indices.len() as u32;
            interior(w, s, &mut indices);
            let interior = IndexRange {
                start,
                count: indices.len() as u32 - start,
            };
            let edges = std::array::from_fn(|e| {
                let edge = Edge::from_index(e);
                (0..=max_diff_for(w, lod))
                    .map(|d| {
                        let start = indices.len() as u32;
                        edge_strip(w, s, s << d, edge, &mut indices);
                        IndexRange {
                            start,
                            count: indices.len() as u32 - start,
                        }
                    })
                    .collect()
            });
            lods.push(LodMasks {
                step: s,
                interior,
                edges,
            });
        }
        Masks { w, indices, lods }
    }

    /// The ranges to draw for a block at `lod` whose neighbours are
    /// `diff[edge]` definition levels coarser (clamped to what the LOD can
    /// stitch). `crack_fixing == false` draws every edge at `d = 0`.
    pub fn ranges(&self, lod: u8, diff: [u8; 4], crack_fixing: bool) -> [IndexRange; 5] {
        let m = &self.lods[lod.min(1) as usize];
        let mut out = [m.interior; 5];
        for e in 0..4 {
            let d = if crack_fixing {
                diff[e].min(m.max_diff())
            } else {
                0
            };
            out[e + 1] = m.edges[e][d as usize];
        }
        out
    }
}

/// Vertex index of `(i, j)`.
#[inline]
fn vid(w: usize, i: usize, j: usize) -> u32 {
    (j * (w + 1) + i) as u32
}

fn interior(w: usize, s: usize, out: &mut Vec<u32>) {
    let mut j = s;
    while j + s < w {
        let mut i = s;
        while i + s < w {
            let a = vid(w, i, j);
            let b = vid(w, i + s, j);
            let c = vid(w, i + s, j + s);
            let d = vid(w, i, j + s);
            // Alternate the diagonal for a more isotropic mesh.
            if ((i / s) + (j / s)).is_multiple_of(2) {
                out.extend_from_slice(&[a, b, c, a, c, d]);
            } else {
                out.extend_from_slice(&[a, b, d, b, c, d]);
            }
            i += s;
        }
        j += s;
    }
}

/// Map the strip's `(p, q)` (along the edge, depth into the block) to `(i, j)`.
#[inline]
fn edge_point(w: usize, edge: Edge, p: usize, q: usize) -> (usize, usize) {
    match edge {
        Edge::Bottom => (p, q),
        Edge::Top => (p, w - q),
        Edge::Left => (q, p),
        Edge::Right => (w - q, p),
    }
}

/// The trapezoid along `edge`: outer chain step `outer` on the edge, inner
/// chain step `s` at depth `s` from `s` to `w − s`.
fn edge_strip(w: usize, s: usize, outer: usize, edge: Edge, out: &mut Vec<u32>) {
    debug_assert!(w.is_multiple_of(outer));
    let outer_pts: Vec<usize> = (0..=w / outer).map(|k| k * outer).collect();
    let inner_pts: Vec<usize> = (1..w / s).map(|k| k * s).collect();
    let mut tri = |a: (usize, usize), b: (usize, usize), c: (usize, usize)| {
        let pa = edge_point(w, edge, a.0, a.1);
        let pb = edge_point(w, edge, b.0, b.1);
        let pc = edge_point(w, edge, c.0, c.1);
        let area = (pb.0 as i64 - pa.0 as i64) * (pc.1 as i64 - pa.1 as i64)
            - (pb.1 as i64 - pa.1 as i64) * (pc.0 as i64 - pa.0 as i64);
        let (ia, ib, ic) = (vid(w, pa.0, pa.1), vid(w, pb.0, pb.1), vid(w, pc.0, pc.1));
        if area > 0 {
            out.extend_from_slice(&[ia, ib, ic]);
        } else if area < 0 {
            out.extend_from_slice(&[ia, ic, ib]);
        }
    };
    let (mut o, mut k) = (0usize, 0usize);
    // Zip the chains: advance whichever next vertex lies further back along
    // the edge (ties: the outer one), keeping triangles well shaped.
    while o + 1 < outer_pts.len() || k + 1 < inner_pts.len() {
        let advance_outer = if o + 1 >= outer_pts.len() {
            false
        } else if k + 1 >= inner_pts.len() {
            true
        } else {
            // The next vertex further back along the edge (ties: the
            // outer one). Comparing the candidate edges' midpoints instead
            // is a comparison of the two chains' steps, the same at every
            // position: with equal steps it always chose the outer chain,
            // and every edge strip became two fans of long thin triangles
            // (smeared normals along every block edge).
            outer_pts[o + 1] <= inner_pts[k + 1]
        };
        if advance_outer {
            tri((outer_pts[o], 0), (outer_pts[o + 1], 0), (inner_pts[k], s));
            o += 1;
        } else {
            tri((outer_pts[o], 0), (inner_pts[k + 1], s), (inner_pts[k], s));
            k += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::{BTreeSet, HashMap};

    fn ij(w: usize, v: u32) -> (i64, i64) {
        ((v as usize % (w + 1)) as i64, (v as usize / (w + 1)) as i64)
    }

    fn area2(w: usize, t: &[u32]) -> i64 {
        let (a, b, c) = (ij(w, t[0]), ij(w, t[1]), ij(w, t[2]));
        (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0)
    }

    fn on_edge(w: usize, edge: Edge, p: (i64, i64)) -> Option<i64> {
        let w = w as i64;
        match edge {
            Edge::Left if p.0 == 0 => Some(p.1),
            Edge::Right if p.0 == w => Some(p.1),
            Edge::Bottom if p.1 == 0 => Some(p.0),
            Edge::Top if p.1 == w => Some(p.0),
            _ => None,
        }
    }

    /// Check that the triangles tile the block square exactly once: all
    /// triangles positive, area sum `W²`, every interior edge used once in
    /// each direction, and every boundary edge once, on the square's border.
    fn assert_tiles_square(w: usize, tris: &[u32]) {
        let mut sum = 0i64;
        let mut half_edges: HashMap<(u32, u32), u32> = HashMap::new();
        for t in tris.chunks(3) {
            let a = area2(w, t);
            assert!(a > 0, "non-positive triangle {t:?}");
            sum += a;
            for k in 0..3 {
                *half_edges.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        assert_eq!(sum, 2 * (w * w) as i64, "area");
        let wi = w as i64;
        for (&(a, b), &n) in &half_edges {
            assert_eq!(n, 1, "half-edge used twice");
            if !half_edges.contains_key(&(b, a)) {
                // Boundary: both ends on the same side of the square.
                let (pa, pb) = (ij(w, a), ij(w, b));
                let border = (pa.0 == pb.0 && (pa.0 == 0 || pa.0 == wi))
                    || (pa.1 == pb.1 && (pa.1 == 0 || pa.1 == wi));
                assert!(border, "open edge inside the square: {pa:?} {pb:?}");
            }
        }
    }

    #[test]
    fn every_combination_tiles_and_uses_the_right_edge_vertices() {
        for w in [4usize, 8, 12, 64] {
            let m = Masks::new(w);
            for lod in 0..2u8 {
                let lm = &m.lods[lod as usize];
                assert_eq!(lm.max_diff(), max_diff_for(w, lod));
                for combo in 0..(lm.max_diff() as usize + 1).pow(2) {
                    // Vary two edges independently, the others follow.
                    let d1 = (combo % (lm.max_diff() as usize + 1)) as u8;
                    let d2 = (combo / (lm.max_diff() as usize + 1)) as u8;
                    let diffs = [d1, d2, d2, d1];
                    let ranges = m.ranges(lod, diffs, true);
                    let tris: Vec<u32> = ranges
                        .iter()
                        .flat_map(|r| {
                            m.indices[r.range().start as usize..r.range().end as usize]
                                .iter()
                                .copied()
                        })
                        .collect();
                    assert_tiles_square(w, &tris);
                    for edge in Edge::ALL {
                        let used: BTreeSet<i64> = tris
                            .iter()
                            .filter_map(|&v| on_edge(w, edge, ij(w, v)))
                            .collect();
                        let step = 1i64 << (diffs[edge as usize] + lod);
                        let expect: BTreeSet<i64> = (0..=w as i64).step_by(step as usize).collect();
                        assert_eq!(
                            used, expect,
                            "w {w} lod {lod} edge {edge:?} d {}",
                            diffs[edge as usize]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn masks_for_w64() {
        let m = Masks::new(64);
        // max_level_difference(64) = 5, so up to 6 definition levels.
        assert_eq!(m.lods[0].max_diff(), 6);
        assert_eq!(m.lods[1].max_diff(), 5);
        // No adaptation: every vertex of the LOD is used.
        let r = m.ranges(1, [0; 4], true);
        let used: BTreeSet<u32> = r
            .iter()
            .flat_map(|r| {
                m.indices[r.start as usize..(r.start + r.count) as usize]
                    .iter()
                    .copied()
            })
            .collect();
        assert_eq!(used.len(), 33 * 33);
        assert!(used.iter().all(|&v| {
            let (i, j) = ij(64, v);
            i % 2 == 0 && j % 2 == 0
        }));
    }

    /// Edge strip triangles are local: none spans more along its edge than
    /// one outer step plus one inner step (the zip alternates between the
    /// chains; it used to consume the outer chain first, making two fans of
    /// triangles as long as the block, which smeared normals along every
    /// block edge).
    #[test]
    fn edge_strip_triangles_are_local() {
        for w in [8usize, 16, 64] {
            let m = Masks::new(w);
            for (lod, l) in m.lods.iter().enumerate() {
                let s = 1usize << lod;
                for (e, ranges) in l.edges.iter().enumerate() {
                    let edge = Edge::from_index(e);
                    for (d, r) in ranges.iter().enumerate() {
                        let outer = s << d;
                        for t in
                            m.indices[r.range().start as usize..r.range().end as usize].chunks(3)
                        {
                            let along: Vec<usize> = t
                                .iter()
                                .map(|&v| {
                                    let (i, j) = (v as usize % (w + 1), v as usize / (w + 1));
                                    if edge.is_vertical() {
                                        j
                                    } else {
                                        i
                                    }
                                })
                                .collect();
                            let span = along.iter().max().unwrap() - along.iter().min().unwrap();
                            assert!(
                                span <= outer + s,
                                "w {w} lod {lod} {edge:?} d {d}: triangle {t:?} spans {span}"
                            );
                        }
                    }
                }
            }
        }
    }
}
