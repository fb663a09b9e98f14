//! From the streaming client's draw list to the renderer's draw list.
//!
//! The client says *which* blocks to draw at which LOD and with which colour
//! block; this module supplies the vertex data and textures:
//!
//! - **Meshes** are built from a leaf's elevation grid ([`BlockMesh::build`])
//!   on worker threads (rayon) and cached per block, keyed by the grid's LOD
//!   (a leaf's grid only changes when its LOD changes: a refine writes LOD 0,
//!   a split gives children their LOD 1 from the parent's full grid, a merge
//!   rebuilds the parent's full grid, identical to the one it had).
//! - While a block's new mesh is being built ([`BuildMode::Async`]) the old
//!   mesh is drawn at the LOD it supports; a block with no mesh at all (just
//!   split) is replaced by its nearest ancestor with a mesh (the parent's
//!   full grid *is* the children's first LOD, so nothing moves), and only
//!   when there is none is the mesh built on the calling thread.
//! - **Crack fixing**: the renderer's per-edge level difference is the
//!   client's `lod_diff` (clamped at 0) when the block and its neighbour are
//!   drawn as the client said; otherwise (substitutions, older meshes) it is
//!   recomputed from the blocks actually drawn, with the same formula
//!   `(level − lod) − (neighbour.level − neighbour.lod)`.
//! - **Textures** come from the colour leaf the client bound to the block
//!   (its own or an ancestor's, with the matching texture transform), built
//!   once per colour block and LOD.

use planet_client::tree::{PartialTree, Samples};
use planet_client::DrawBlock as ClientBlock;
use planet_core::format::Header;
use planet_core::{BlockId, Datum, Edge};
use planet_render::mesh::Border;
use planet_render::{BlockMesh, BlockTexture, ColourRef, DrawBlock};
use std::collections::{HashMap, HashSet};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::Arc;

/// How missing meshes are built.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BuildMode {
    /// Build every missing mesh before returning (headless, reproducible).
    Sync,
    /// Build on worker threads; draw what exists meanwhile (interactive).
    Async,
}

struct MeshEntry {
    /// LOD of the grid the mesh was built from (1: only even samples valid).
    lod: u8,
    /// Which neighbours' samples its edge normals used ([`Border::key`]).
    border: [u8; 4],
    mesh: Arc<BlockMesh>,
    last_used: u64,
}

struct TexEntry {
    full: bool,
    tex: Arc<BlockTexture>,
    last_used: u64,
}

/// Counters of the last [`SceneBuilder::prepare`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SceneStats {
    /// Meshes built on the calling thread.
    pub built_inline: usize,
    /// Mesh builds queued to the workers.
    pub queued: usize,
    /// Mesh builds still running.
    pub pending: usize,
    /// Blocks drawn with an older mesh (coarser LOD) than the client asked.
    pub stale: usize,
    /// Blocks replaced by an ancestor's mesh.
    pub substituted: usize,
    /// Cached meshes.
    pub cached_meshes: usize,
}

/// Keeps meshes and textures for the client's blocks.
pub struct SceneBuilder {
    datum: Datum,
    scale: f64,
    offset: f64,
    w: usize,
    colour_w: usize,
    meshes: HashMap<BlockId, MeshEntry>,
    pending: HashSet<(BlockId, u8, [u8; 4])>,
    done_tx: Sender<Built>,
    done_rx: Receiver<Built>,
    textures: HashMap<BlockId, TexEntry>,
    frame: u64,
    /// Drop cached meshes and textures unused for this many frames.
    pub keep_frames: u64,
    /// Counters of the last frame.
    pub stats: SceneStats,
}

/// A finished mesh build: block, grid LOD, border key, mesh.
type Built = (BlockId, u8, [u8; 4], BlockMesh);

/// What a block's mesh is built from: its grid and its same-level
/// neighbours' grids (for seamless edge normals, [`Border`]).
struct MeshInput {
    id: BlockId,
    lod: u8,
    grid: Vec<i16>,
    /// Per edge: the neighbour, its edge facing us, its grid, whether at LOD 0.
    neighbours: [Option<NeighbourGrid>; 4],
}

/// A same-level neighbour, its edge facing the block, its grid, and whether
/// the grid is at LOD 0.
type NeighbourGrid = (BlockId, Edge, Vec<i16>, bool);

impl MeshInput {
    fn key(&self) -> [u8; 4] {
        let mut k = [0u8; 4];
        for (e, n) in self.neighbours.iter().enumerate() {
            k[e] = match n {
                Some((.., true)) => 2,
                Some(_) => 1,
                None => 0,
            };
        }
        k
    }
}

/// The border key of `id`'s neighbours now, without copying grids.
fn border_key(tree: &PartialTree, id: &BlockId) -> [u8; 4] {
    let et = tree.elevation();
    let mut k = [0u8; 4];
    for (e, edge) in Edge::ALL.iter().enumerate() {
        let (nb, _) = id.neighbour(*edge);
        if let Some(n) = et.get(&nb) {
            if matches!(n.samples, Some(Samples::Elevation(_))) {
                k[e] = if n.lod == 0 { 2 } else { 1 };
            }
        }
    }
    k
}

fn mesh_input(tree: &PartialTree, id: BlockId, lod: u8, grid: &[i16]) -> MeshInput {
    let et = tree.elevation();
    let neighbours = Edge::ALL.map(|edge| {
        let (nb, back) = id.neighbour(edge);
        let n = et.get(&nb)?;
        match n.samples.as_ref() {
            Some(Samples::Elevation(g)) => Some((nb, back, g.clone(), n.lod == 0)),
            _ => None,
        }
    });
    MeshInput {
        id,
        lod,
        grid: grid.to_vec(),
        neighbours,
    }
}

fn build_mesh(datum: &Datum, w: usize, scale: f64, offset: f64, m: &MeshInput) -> BlockMesh {
    let mut border = Border::default();
    for (edge, n) in Edge::ALL.iter().zip(&m.neighbours) {
        if let Some((nb, back, g, lod0)) = n {
            border.set_from_neighbour(datum, *edge, *nb, *back, w, g, *lod0, scale, offset);
        }
    }
    BlockMesh::build_with_border(datum, m.id, w, &m.grid, scale, offset, &border)
}

fn definition(level: u8, lod: u8) -> i32 {
    level as i32 - lod as i32
}

impl SceneBuilder {
    /// A builder for the database described by `header`.
    pub fn new(header: &Header) -> SceneBuilder {
        let (done_tx, done_rx) = channel();
        SceneBuilder {
            datum: header.datum,
            scale: header.elevation_scale as f64,
            offset: header.elevation_offset as f64,
            w: header.elevation.block_width as usize,
            colour_w: header.colour.as_ref().map_or(0, |c| c.block_width as usize),
            meshes: HashMap::new(),
            pending: HashSet::new(),
            done_tx,
            done_rx,
            textures: HashMap::new(),
            frame: 0,
            keep_frames: 120,
            stats: SceneStats::default(),
        }
    }

    /// Chord sag (metres) of the coarsest triangles in `blocks`: how far a
    /// flat triangle dips below its vertices, to lower the far plane's
    /// minimum radius (see `RenderSettings::r_min`).
    pub fn max_sag(&self, blocks: &[DrawBlock]) -> f64 {
        let r = self.datum.equatorial_radius();
        blocks
            .iter()
            .map(|b| {
                // Angle spanned by one triangle's diagonal.
                let step = (1u64 << b.lod) as f64;
                let theta = std::f64::consts::FRAC_PI_2 / (1u64 << b.id.level) as f64 * step
                    / self.w as f64
                    * std::f64::consts::SQRT_2;
                r * theta * theta / 8.0
            })
            .fold(0.0, f64::max)
    }

    /// The renderer's draw list for the client's `draw` list over `tree`.
    pub fn prepare(
        &mut self,
        tree: &PartialTree,
        draw: &[ClientBlock],
        mode: BuildMode,
    ) -> Vec<DrawBlock> {
        self.frame += 1;
        let frame = self.frame;
        let mut stats = SceneStats::default();
        // 1. Finished background builds.
        while let Ok((id, lod, border, mesh)) = self.done_rx.try_recv() {
            self.pending.remove(&(id, lod, border));
            self.meshes.insert(
                id,
                MeshEntry {
                    lod,
                    border,
                    mesh: Arc::new(mesh),
                    last_used: frame,
                },
            );
        }
        let et = tree.elevation();
        // 2. Per client block: its mesh, an older one, or a substitute.
        let mut inline: Vec<MeshInput> = Vec::new();
        let mut wanted: Vec<&ClientBlock> = Vec::with_capacity(draw.len());
        for d in draw {
            let Some(node) = et.get(&d.block) else {
                continue;
            };
            let Some(Samples::Elevation(grid)) = node.samples.as_ref() else {
                continue;
            };
            let key = border_key(tree, &d.block);
            match self.meshes.get(&d.block) {
                Some(e) if e.lod == node.lod && e.border == key => {}
                other => {
                    let have_other = other.is_some();
                    let ancestor = !have_other && self.ancestor_with_mesh(d.block).is_some();
                    if mode == BuildMode::Sync || (!have_other && !ancestor) {
                        inline.push(mesh_input(tree, d.block, node.lod, grid));
                    } else if self.pending.insert((d.block, node.lod, key)) {
                        stats.queued += 1;
                        let input = mesh_input(tree, d.block, node.lod, grid);
                        let tx = self.done_tx.clone();
                        let (datum, w, scale, offset) =
                            (self.datum, self.w, self.scale, self.offset);
                        rayon::spawn(move || {
                            let m = build_mesh(&datum, w, scale, offset, &input);
                            let _ = tx.send((input.id, input.lod, input.key(), m));
                        });
                    }
                }
            }
            wanted.push(d);
        }
        if !inline.is_empty() {
            use rayon::prelude::*;
            stats.built_inline = inline.len();
            let (datum, w, scale, offset) = (self.datum, self.w, self.scale, self.offset);
            let built: Vec<Built> = inline
                .par_iter()
                .map(|m| {
                    (
                        m.id,
                        m.lod,
                        m.key(),
                        build_mesh(&datum, w, scale, offset, m),
                    )
                })
                .collect();
            for (id, lod, border, m) in built {
                self.pending.remove(&(id, lod, border));
                self.meshes.insert(
                    id,
                    MeshEntry {
                        lod,
                        border,
                        mesh: Arc::new(m),
                        last_used: frame,
                    },
                );
            }
        }
        // 3. The blocks actually drawn: (lod, mesh, as the client said).
        let mut chosen: HashMap<BlockId, (u8, Arc<BlockMesh>, bool)> = HashMap::new();
        let mut client_of: HashMap<BlockId, &ClientBlock> = HashMap::new();
        for d in wanted {
            let (id, lod) = (d.block, d.lod);
            client_of.insert(id, d);
            if let Some(e) = self.meshes.get(&id) {
                let l = lod.max(e.lod);
                if l != lod {
                    stats.stale += 1;
                }
                chosen.insert(id, (l, e.mesh.clone(), l == lod));
            } else if let Some((a, l, m)) = self.ancestor_with_mesh(id) {
                stats.substituted += 1;
                chosen.insert(a, (l, m, false));
            }
        }
        // Remove blocks covered by a drawn ancestor (substitutes).
        let ids: Vec<BlockId> = chosen.keys().copied().collect();
        for id in ids {
            if (0..id.level).any(|l| chosen.contains_key(&id.ancestor(l))) {
                chosen.remove(&id);
            }
        }
        // 4. Neighbour differences and colour.
        let mut out = Vec::with_capacity(chosen.len());
        let mut keys: Vec<BlockId> = chosen.keys().copied().collect();
        keys.sort();
        for id in keys {
            let (lod, mesh, as_client) = chosen[&id].clone();
            let mut diff = [0u8; 4];
            for (k, e) in Edge::ALL.iter().enumerate() {
                let client_nb = if as_client {
                    client_of[&id].neighbours[k]
                } else {
                    None
                };
                if let Some(n) = client_nb {
                    if chosen.get(&n.block).is_some_and(|c| c.2) {
                        diff[k] = n.lod_diff.clamp(0, 255) as u8;
                        continue;
                    }
                }
                let (nb, _) = id.neighbour(*e);
                let cover = (0..=nb.level)
                    .rev()
                    .map(|l| nb.ancestor(l))
                    .find_map(|a| chosen.get(&a).map(|c| (a, c.0)));
                if let Some((a, alod)) = cover {
                    let d = definition(id.level, lod) - definition(a.level, alod);
                    diff[k] = d.clamp(0, 255) as u8;
                }
            }
            let colour = self.colour_for(tree, id, client_of.get(&id).copied(), frame);
            out.push(DrawBlock {
                id,
                lod,
                neighbour_lod_diff: diff,
                mesh,
                colour,
            });
        }
        // 5. Keep what was used, and the parents of drawn blocks (they stand
        // in for their children right after a split).
        for b in &out {
            if let Some(e) = self.meshes.get_mut(&b.id) {
                e.last_used = frame;
            }
            if let Some(p) = b.id.parent() {
                if let Some(e) = self.meshes.get_mut(&p) {
                    e.last_used = frame;
                }
            }
        }
        let keep = self.keep_frames;
        self.meshes.retain(|_, e| frame - e.last_used <= keep);
        self.textures.retain(|_, e| frame - e.last_used <= keep);
        stats.pending = self.pending.len();
        stats.cached_meshes = self.meshes.len();
        self.stats = stats;
        out
    }

    fn ancestor_with_mesh(&self, id: BlockId) -> Option<(BlockId, u8, Arc<BlockMesh>)> {
        (0..id.level).rev().find_map(|l| {
            let a = id.ancestor(l);
            self.meshes.get(&a).map(|e| (a, e.lod, e.mesh.clone()))
        })
    }

    fn texture(
        &mut self,
        tree: &PartialTree,
        id: BlockId,
        frame: u64,
    ) -> Option<Arc<BlockTexture>> {
        let ct = tree.colour()?;
        let node = ct.get(&id)?;
        let Some(Samples::Colour { lod1, full }) = node.samples.as_ref() else {
            return None;
        };
        let has_full = full.is_some();
        if let Some(e) = self.textures.get_mut(&id) {
            if e.full == has_full {
                e.last_used = frame;
                return Some(e.tex.clone());
            }
        }
        let w = self.colour_w;
        if lod1.len() != (w / 2) * (w / 2) || full.as_ref().is_some_and(|f| f.len() != w * w) {
            return None;
        }
        let tex = Arc::new(BlockTexture::new(id, w, full.as_deref(), lod1));
        self.textures.insert(
            id,
            TexEntry {
                full: has_full,
                tex: tex.clone(),
                last_used: frame,
            },
        );
        Some(tex)
    }

    fn colour_for(
        &mut self,
        tree: &PartialTree,
        id: BlockId,
        client: Option<&ClientBlock>,
        frame: u64,
    ) -> Option<ColourRef> {
        let ct = tree.colour()?;
        // The client's binding, or the colour leaf covering the block.
        let bound = client
            .and_then(|c| c.colour.map(|b| b.block))
            .or_else(|| ct.covering(&id).filter(|n| !n.split).map(|n| n.id));
        if let Some(b) = bound {
            if let Some(t) = self.texture(tree, b, frame) {
                return ColourRef::for_block(t, id);
            }
        }
        // A substitute over a split colour block: any cached ancestor texture.
        (0..=id.level).rev().find_map(|l| {
            let a = id.ancestor(l);
            let e = self.textures.get_mut(&a)?;
            e.last_used = frame;
            ColourRef::for_block(e.tex.clone(), id)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;
    use planet_client::{Camera, Client, ClientConfig};
    use planet_testkit::testdb::{FakeServer, TestDb, TestDbConfig};

    fn converge(client: &mut Client, db: &TestDb, cam: &Camera, frames: usize) -> Vec<ClientBlock> {
        let mut server = FakeServer::new(0);
        let mut last = vec![];
        for _ in 0..frames {
            let out = client.frame(cam, 1.0 / 60.0);
            server.submit(&out);
            for (id, bytes) in server.tick(db) {
                client.deliver(id, Ok(bytes));
            }
            last = out.draw;
        }
        last
    }

    #[test]
    fn draw_list_is_a_cut_with_client_diffs_and_colour() {
        let db = TestDb::build(TestDbConfig::default());
        let mut client = Client::new(
            db.header.clone(),
            ClientConfig {
                decode_threads: 0,
                // The thesis's spacing criterion refines the smooth
                // synthetic database; the policy is not what is tested.
                ..ClientConfig::for_policy(planet_client::Policy::Thesis, 1.0)
            },
        )
        .unwrap();
        let r = 6_371_000.0;
        let cam = Camera::look_at(DVec3::new(r * 1.3, 0.2 * r, 0.3 * r), DVec3::ZERO, DVec3::Z);
        let mut scene = SceneBuilder::new(&db.header);
        let mut max_level = 0;
        for _ in 0..6 {
            let draw = converge(&mut client, &db, &cam, 10);
            let blocks = scene.prepare(client.tree(), &draw, BuildMode::Sync);
            assert_eq!(blocks.len(), draw.len());
            // Same diffs as the client when nothing was substituted.
            for (b, d) in blocks.iter().zip({
                let mut s = draw.clone();
                s.sort_by_key(|d| d.block);
                s
            }) {
                assert_eq!(b.id, d.block);
                assert_eq!(b.lod, d.lod);
                for k in 0..4 {
                    let expect = d.neighbours[k].map_or(0, |n| n.lod_diff.max(0) as u8);
                    assert_eq!(b.neighbour_lod_diff[k], expect);
                }
                assert!(b.colour.is_some());
                max_level = max_level.max(b.id.level);
            }
        }
        assert!(max_level >= 2, "the client refined ({max_level})");
        // Async: a fresh builder substitutes nothing it cannot (first frame
        // builds inline), later frames reuse.
        let draw = converge(&mut client, &db, &cam, 2);
        let mut scene2 = SceneBuilder::new(&db.header);
        let a = scene2.prepare(client.tree(), &draw, BuildMode::Async);
        assert!(!a.is_empty());
        let b = scene2.prepare(client.tree(), &draw, BuildMode::Async);
        assert_eq!(scene2.stats.built_inline, 0);
        assert_eq!(a.len(), b.len());
    }
}
