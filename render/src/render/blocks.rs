//! What the caller draws: blocks with their meshes and colour textures.

use crate::mesh::BlockMesh;
use planet_core::lod::Rgb;
use planet_core::BlockId;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

pub(super) static NEXT_TEXTURE_VERSION: AtomicU64 = AtomicU64::new(1);

/// A block's colour texture, with its LODs as mip levels (finest first).
#[derive(Debug, Clone)]
pub struct BlockTexture {
    /// The colour block.
    pub id: BlockId,
    /// Mip levels, finest first, each `side >> k` wide, RGB8 row-major (`j`
    /// along `v`). Levels below the streamed ones are box-filtered here
    /// ("virtual" LODs, thesis §4.4.3).
    pub levels: Vec<(usize, Vec<Rgb>)>,
    /// Unique per built texture (cache key).
    pub version: u64,
}

impl BlockTexture {
    /// From the filtered LOD 1 `(W/2)²` grid and, when loaded, the full LOD 0
    /// `W²` grid of a colour block of width `w`.
    pub fn new(id: BlockId, w: usize, full: Option<&[Rgb]>, lod1: &[Rgb]) -> BlockTexture {
        let mut levels = Vec::new();
        if let Some(full) = full {
            assert_eq!(full.len(), w * w);
            levels.push((w, full.to_vec()));
        }
        assert_eq!(lod1.len(), (w / 2) * (w / 2));
        levels.push((w / 2, lod1.to_vec()));
        while let Some((side, last)) = levels.last() {
            let side = *side;
            if side < 2 || side % 2 != 0 {
                break;
            }
            let next = planet_core::lod::colour_filter(last, side);
            levels.push((side / 2, next));
        }
        BlockTexture {
            id,
            levels,
            version: NEXT_TEXTURE_VERSION.fetch_add(1, Ordering::Relaxed),
        }
    }
}

/// A block's colour source: its own texture or an ancestor's, with the 2×3
/// texture transform (here scale + offset) from the block's `(i/W, j/W)`
/// coordinates to the texture's (thesis §4.4.3).
#[derive(Debug, Clone)]
pub struct ColourRef {
    /// The texture.
    pub texture: Arc<BlockTexture>,
    /// Scale of the transform.
    pub scale: [f32; 2],
    /// Offset of the transform.
    pub offset: [f32; 2],
}

impl ColourRef {
    /// The transform for drawing `block` with `texture`, which must belong to
    /// `block` or one of its ancestors.
    pub fn for_block(texture: Arc<BlockTexture>, block: BlockId) -> Option<ColourRef> {
        let t = texture.id;
        if !t.contains(&block) {
            return None;
        }
        let dl = block.level - t.level;
        let k = (1u64 << dl) as f64;
        let scale = 1.0 / k;
        let ox = (block.x as u64 - ((t.x as u64) << dl)) as f64 / k;
        let oy = (block.y as u64 - ((t.y as u64) << dl)) as f64 / k;
        Some(ColourRef {
            texture,
            scale: [scale as f32, scale as f32],
            offset: [ox as f32, oy as f32],
        })
    }
}

/// One block to draw this frame.
#[derive(Debug, Clone)]
pub struct DrawBlock {
    /// The block.
    pub id: BlockId,
    /// The selected LOD: 0 the full grid, 1 the first (step 2).
    pub lod: u8,
    /// Per edge (Left, Top, Right, Bottom): how many definition levels
    /// coarser the neighbour on that edge is (0: same or finer).
    pub neighbour_lod_diff: [u8; 4],
    /// The vertex data.
    pub mesh: Arc<BlockMesh>,
    /// Colour, or `None` to shade by altitude.
    pub colour: Option<ColourRef>,
}
