//! Block vertex data, built off the render thread from an elevation grid.
//!
//! Positions are computed in f64 on the datum with core's equal-angle
//! sampling exactly as core does (`sample_coord(x·W + i, W·2^L)`,
//! `plane_from_angle`, `Face::cube_point`), so a sample shared by two blocks
//! (also across cube edges, and with a coarser block whose sample `k` is this
//! block's sample `k·2^d`) has a bit-identical f64 position. The block centre
//! is kept in f64 and the vertices are stored as f32 offsets from it plus an
//! f16 residual; camera-relative rendering adds `centre − eye` as two f32
//! parts per block with one final rounding ([`crate::camera_relative`]).

use glam::DVec3;
use planet_core::cube::{normalize, plane_from_angle, sample_coord};
use planet_core::{BlockId, Datum, Edge};
use std::sync::atomic::{AtomicU64, Ordering};

/// One vertex as uploaded to the GPU (44 bytes).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Vertex {
    /// Position relative to the block centre, metres: `f32(p − centre)`.
    pub pos: [f32; 3],
    /// Unit surface normal (planet frame).
    pub normal: [f32; 3],
    /// Texture coordinate in the block, `(i/W, j/W)`.
    pub uv: [f32; 2],
    /// Altitude above the datum in metres.
    pub alt: f32,
    /// The residual `p − centre − pos` as f16 bits `[x, y, z, 0]`
    /// ([`crate::camera_relative::low_part_f16`]).
    pub pos_lo: [u16; 4],
}

/// Largest altitude magnitude (metres) a vertex is built with.
pub const MAX_ABS_ALTITUDE: f64 = 1.0e9;

static NEXT_VERSION: AtomicU64 = AtomicU64::new(1);

/// Grid coordinates of sample `along` on `edge`, `inward` samples inside.
fn edge_sample(w: usize, edge: Edge, along: usize, inward: usize) -> (usize, usize) {
    match edge {
        Edge::Left => (inward, along),
        Edge::Right => (w - inward, along),
        Edge::Bottom => (along, inward),
        Edge::Top => (along, w - inward),
    }
}

/// The samples just outside a block's edges, taken from the same-level
/// neighbour across each edge (also across cube edges): with them the
/// normals of edge vertices are central differences, computed from the
/// same samples on both sides, so lighting has no seam where two blocks of
/// one level meet. Without them (no same-level neighbour with samples)
/// edge normals are one-sided.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Border {
    /// Per edge (`Edge::ALL` order), per sample along the edge (`0..=W`):
    /// the positions one and two samples outside, when known. Two outside
    /// is a LOD 1 position of the neighbour (valid at either of its LODs);
    /// one outside needs the neighbour at LOD 0.
    pub outside: [OutsideRings; 4],
}

/// The positions one and two samples outside one edge (see [`Border`]).
pub type OutsideRings = (Option<Vec<[f64; 3]>>, Option<Vec<[f64; 3]>>);

impl Border {
    /// Which outside rings are known, per edge: 0 none, 1 two outside only,
    /// 2 both (a mesh built with a smaller key than the current one can be
    /// rebuilt).
    pub fn key(&self) -> [u8; 4] {
        let mut k = [0u8; 4];
        for (e, (near, far)) in self.outside.iter().enumerate() {
            k[e] = match (near.is_some(), far.is_some()) {
                (true, true) => 2,
                (false, true) => 1,
                _ => 0,
            };
        }
        k
    }

    /// Set `edge`'s outside samples from the same-level neighbour `nb`
    /// (whose edge `back` faces this block) and its `(W+1)²` grid;
    /// `lod0`: whether the neighbour's full grid is valid (else only its
    /// LOD 1 samples are used).
    #[allow(clippy::too_many_arguments)]
    pub fn set_from_neighbour(
        &mut self,
        datum: &Datum,
        edge: Edge,
        nb: BlockId,
        back: Edge,
        w: usize,
        grid: &[i16],
        lod0: bool,
        scale: f64,
        offset: f64,
    ) {
        let side = w + 1;
        if grid.len() != side * side || w < 4 {
            return;
        }
        let ring = |inward: usize| -> Vec<[f64; 3]> {
            (0..=w)
                .map(|k| {
                    // Shared edge samples have the same index along the
                    // edge on both sides (see the tests).
                    let (i, j) = edge_sample(w, back, k, inward);
                    sample_position(
                        datum,
                        nb,
                        w,
                        i,
                        j,
                        altitude(grid[j * side + i], scale, offset),
                    )
                })
                .collect()
        };
        let e = edge as usize;
        self.outside[e] = (lod0.then(|| ring(1)), Some(ring(2)));
    }
}

/// Altitude in metres of a stored sample, clamped so that a hostile header
/// scale (any finite f32 passes `format.rs`) times an int16 extreme cannot
/// overflow the f32 casts.
fn altitude(q: i16, scale: f64, offset: f64) -> f64 {
    (q as f64 * scale + offset).clamp(-MAX_ABS_ALTITUDE, MAX_ABS_ALTITUDE)
}

/// The vertex array of one block, both LODs in one `(W+1)²` array.
#[derive(Debug, Clone)]
pub struct BlockMesh {
    /// The block.
    pub id: BlockId,
    /// Block width `W`.
    pub w: usize,
    /// Block centre (the datum point under the block's middle, at the mean of
    /// the minimum and maximum altitude), planet frame, metres.
    pub centre: [f64; 3],
    /// Vertices, row-major `j·(W+1) + i`.
    pub vertices: Vec<Vertex>,
    /// Unique per built mesh: the GPU cache key is `(id, version)`.
    pub version: u64,
    /// Minimum and maximum altitude of the LOD 1 samples (metres).
    pub alt_range: (f32, f32),
    /// Largest distance of a LOD 1 vertex from `centre` (bounding sphere).
    pub radius: f64,
}

/// Planet-frame position of sample `(i, j)` of block `id` of width `w` at
/// altitude `h` (bit-identical for shared samples).
pub fn sample_position(
    datum: &Datum,
    id: BlockId,
    w: usize,
    i: usize,
    j: usize,
    h: f64,
) -> [f64; 3] {
    let n = (w as u64) << id.level;
    let s = sample_coord(id.x as u64 * w as u64 + i as u64, n);
    let t = sample_coord(id.y as u64 * w as u64 + j as u64, n);
    let dir = normalize(id.face.cube_point(plane_from_angle(s), plane_from_angle(t)));
    datum.position(dir, h)
}

impl BlockMesh {
    /// Build a block's vertices from its elevation grid `(W+1)²` (row-major,
    /// `j` along `v`); altitude = `grid · scale + offset` metres.
    ///
    /// The LOD 1 samples (even `i` and `j`) must be valid; the odd ones only
    /// matter when the block is drawn at LOD 0. Normals of LOD 1 samples use
    /// LOD 1 neighbours only, so they are valid either way.
    pub fn build(
        datum: &Datum,
        id: BlockId,
        w: usize,
        grid: &[i16],
        scale: f64,
        offset: f64,
    ) -> BlockMesh {
        Self::build_with_border(datum, id, w, grid, scale, offset, &Border::default())
    }

    /// [`BlockMesh::build`] with the samples outside its edges (seamless
    /// edge normals where they are known).
    pub fn build_with_border(
        datum: &Datum,
        id: BlockId,
        w: usize,
        grid: &[i16],
        scale: f64,
        offset: f64,
        border: &Border,
    ) -> BlockMesh {
        let side = w + 1;
        assert_eq!(grid.len(), side * side, "grid must be (W+1)²");
        assert!(w >= 4 && w.is_multiple_of(2));
        let alt = |i: usize, j: usize| altitude(grid[j * side + i], scale, offset);
        // Altitude range over the LOD 1 samples.
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for j in (0..side).step_by(2) {
            for i in (0..side).step_by(2) {
                let a = alt(i, j);
                lo = lo.min(a);
                hi = hi.max(a);
            }
        }
        let centre = sample_position(datum, id, w, w / 2, w / 2, 0.5 * (lo + hi));
        let positions: Vec<[f64; 3]> = (0..side * side)
            .map(|k| {
                let (i, j) = (k % side, k / side);
                sample_position(datum, id, w, i, j, alt(i, j))
            })
            .collect();
        let mut radius = 0.0f64;
        let mut vertices = Vec::with_capacity(side * side);
        for j in 0..side {
            for i in 0..side {
                let p = positions[j * side + i];
                let rel = DVec3::from(p) - DVec3::from(centre);
                let lod1 = i % 2 == 0 && j % 2 == 0;
                if lod1 {
                    radius = radius.max(rel.length());
                }
                let rel = rel.to_array();
                // Central differences with the LOD's step; on the border
                // with the neighbour's samples outside when known, else
                // one-sided.
                let st = if lod1 { 2 } else { 1 };
                let outside = |e: Edge, along: usize| -> Option<[f64; 3]> {
                    let (near, far) = &border.outside[e as usize];
                    let ring = if st == 1 { near } else { far };
                    ring.as_ref().and_then(|r| r.get(along).copied())
                };
                let at = |i: usize, j: usize| positions[j * side + i];
                let lo_u = if i >= st {
                    Some(at(i - st, j))
                } else {
                    outside(Edge::Left, j)
                };
                let hi_u = if i + st <= w {
                    Some(at(i + st, j))
                } else {
                    outside(Edge::Right, j)
                };
                let lo_v = if j >= st {
                    Some(at(i, j - st))
                } else {
                    outside(Edge::Bottom, i)
                };
                let hi_v = if j + st <= w {
                    Some(at(i, j + st))
                } else {
                    outside(Edge::Top, i)
                };
                let du = DVec3::from(hi_u.unwrap_or(at((i + st).min(w), j)))
                    - DVec3::from(lo_u.unwrap_or(at(i.saturating_sub(st), j)));
                let dv = DVec3::from(hi_v.unwrap_or(at(i, (j + st).min(w))))
                    - DVec3::from(lo_v.unwrap_or(at(i, j.saturating_sub(st))));
                let normal = match du.cross(dv).try_normalize() {
                    Some(n) => n.to_array(),
                    // The sample's direction: `normalize(p)` is NaN when the
                    // point is at the planet centre (altitude = −radius).
                    None => sample_position(&Datum::Sphere { radius: 1.0 }, id, w, i, j, 0.0),
                };
                let (pos, _) = crate::camera_relative::split_f32(rel);
                vertices.push(Vertex {
                    pos,
                    pos_lo: crate::camera_relative::low_part_f16(rel, pos),
                    normal: [normal[0] as f32, normal[1] as f32, normal[2] as f32],
                    uv: [i as f32 / w as f32, j as f32 / w as f32],
                    alt: alt(i, j) as f32,
                });
            }
        }
        BlockMesh {
            id,
            w,
            centre,
            vertices,
            version: NEXT_VERSION.fetch_add(1, Ordering::Relaxed),
            alt_range: (lo as f32, hi as f32),
            radius,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use planet_core::Face;

    #[test]
    fn shared_edges_are_identical_in_f64_across_faces_and_levels() {
        let datum = Datum::WGS84;
        let w = 16;
        for f in Face::ALL {
            let b = BlockId::new(f, 2, 0, 3).unwrap();
            for edge in Edge::ALL {
                let (nb, back) = b.neighbour(edge);
                for k in 0..=w {
                    let at = |blk: BlockId, e: Edge, k: usize| {
                        let (i, j) = match e {
                            Edge::Left => (0, k),
                            Edge::Right => (w, k),
                            Edge::Bottom => (k, 0),
                            Edge::Top => (k, w),
                        };
                        sample_position(&datum, blk, w, i, j, 123.0)
                    };
                    assert_eq!(at(b, edge, k), at(nb, back, k));
                }
                // A child of the neighbour, one level finer: its every other
                // edge sample is one of ours.
                let (nb, back) = b.neighbour(edge);
                let child = match back {
                    Edge::Left => nb.child(0),
                    Edge::Right => nb.child(1),
                    Edge::Bottom => nb.child(0),
                    Edge::Top => nb.child(2),
                };
                for k in 0..=w / 2 {
                    let (i, j) = match back {
                        Edge::Left => (0, 2 * k),
                        Edge::Right => (w, 2 * k),
                        Edge::Bottom => (2 * k, 0),
                        Edge::Top => (2 * k, w),
                    };
                    let fine = sample_position(&datum, child, w, i, j, 5.0);
                    let (ci, cj) = match edge {
                        Edge::Left => (0, k),
                        Edge::Right => (w, k),
                        Edge::Bottom => (k, 0),
                        Edge::Top => (k, w),
                    };
                    // The child is the first half along the edge.
                    let coarse = sample_position(&datum, b, w, ci, cj, 5.0);
                    assert_eq!(fine, coarse, "{b:?} {edge:?} {k}");
                }
            }
        }
    }

    #[test]
    fn build_is_centred_and_normals_point_out() {
        let w = 8;
        let grid: Vec<i16> = (0..81).map(|k| (k % 7) as i16 * 10).collect();
        let id = BlockId::new(Face::new(4).unwrap(), 3, 2, 5).unwrap();
        let m = BlockMesh::build(&Datum::WGS84, id, w, &grid, 1.0, -20.0);
        assert_eq!(m.vertices.len(), 81);
        let c = normalize(m.centre);
        for v in &m.vertices {
            let n = v.normal;
            assert!(n[0] as f64 * c[0] + n[1] as f64 * c[1] + n[2] as f64 * c[2] > 0.9);
        }
        let m2 = BlockMesh::build(&Datum::WGS84, id, w, &grid, 1.0, -20.0);
        assert_ne!(m.version, m2.version);
        assert_eq!(m.alt_range.0, -20.0);
    }

    /// A bumpy field of the sample's direction: shared samples agree.
    fn bumpy_grid(id: BlockId, w: usize) -> Vec<i16> {
        let mut g = Vec::with_capacity((w + 1) * (w + 1));
        for j in 0..=w {
            for i in 0..=w {
                let d = sample_position(&Datum::Sphere { radius: 1.0 }, id, w, i, j, 0.0);
                let h = 2000.0 * (400.0 * d[0]).sin() * (330.0 * d[1]).cos()
                    + 1500.0 * (270.0 * d[2]).sin();
                g.push(h as i16);
            }
        }
        g
    }

    fn normal_at(m: &BlockMesh, w: usize, e: Edge, k: usize) -> [f32; 3] {
        let (i, j) = edge_sample(w, e, k, 0);
        m.vertices[j * (w + 1) + i].normal
    }

    fn gap(a: [f32; 3], b: [f32; 3]) -> f32 {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    }

    #[test]
    fn edge_normals_agree_with_the_neighbours_samples_across_blocks_and_faces() {
        let datum = Datum::WGS84;
        let w = 16;
        let mut worst_one_sided = 0.0f32;
        for f in Face::ALL {
            // A block on the face's corner: two of its edges are cube edges.
            let a = BlockId::new(f, 6, 0, 63).unwrap();
            let ga = bumpy_grid(a, w);
            for edge in Edge::ALL {
                let (b, back) = a.neighbour(edge);
                let gb = bumpy_grid(b, w);
                for lod0 in [true, false] {
                    let mut ba = Border::default();
                    ba.set_from_neighbour(&datum, edge, b, back, w, &gb, lod0, 1.0, 0.0);
                    let mut bb = Border::default();
                    bb.set_from_neighbour(&datum, back, a, edge, w, &ga, lod0, 1.0, 0.0);
                    let ma = BlockMesh::build_with_border(&datum, a, w, &ga, 1.0, 0.0, &ba);
                    let mb = BlockMesh::build_with_border(&datum, b, w, &gb, 1.0, 0.0, &bb);
                    let plain = BlockMesh::build(&datum, a, w, &ga, 1.0, 0.0);
                    let plain_b = BlockMesh::build(&datum, b, w, &gb, 1.0, 0.0);
                    // Every vertex with the outside samples it needs: all
                    // when the neighbour is at LOD 0, the LOD 1 ones (even
                    // index) otherwise. The corners also need the other
                    // edges' neighbours, so they are left out.
                    for k in 1..w {
                        if !lod0 && k % 2 == 1 {
                            continue;
                        }
                        let (na, nb) = (normal_at(&ma, w, edge, k), normal_at(&mb, w, back, k));
                        assert!(
                            gap(na, nb) < 1e-5,
                            "{a:?} {edge:?} / {b:?} {back:?} at {k}: {na:?} vs {nb:?}"
                        );
                        worst_one_sided = worst_one_sided.max(gap(
                            normal_at(&plain, w, edge, k),
                            normal_at(&plain_b, w, back, k),
                        ));
                    }
                }
            }
        }
        // Without the neighbours' samples the same field has seams.
        assert!(
            worst_one_sided > 0.05,
            "one-sided normals differ by {worst_one_sided}"
        );
    }

    #[test]
    fn border_key_counts_the_known_rings() {
        let datum = Datum::WGS84;
        let w = 8;
        let a = BlockId::new(Face::new(0).unwrap(), 3, 2, 2).unwrap();
        let (b, back) = a.neighbour(Edge::Top);
        let g = vec![0i16; 81];
        let mut border = Border::default();
        assert_eq!(border.key(), [0, 0, 0, 0]);
        border.set_from_neighbour(&datum, Edge::Top, b, back, w, &g, false, 1.0, 0.0);
        assert_eq!(border.key(), [0, 1, 0, 0]);
        border.set_from_neighbour(&datum, Edge::Top, b, back, w, &g, true, 1.0, 0.0);
        assert_eq!(border.key(), [0, 2, 0, 0]);
        // A grid of the wrong size is ignored.
        border.set_from_neighbour(&datum, Edge::Left, b, back, w, &g[..80], true, 1.0, 0.0);
        assert_eq!(border.key(), [0, 2, 0, 0]);
    }
}
