//! A synthetic in-memory database and a fake server, for tests and
//! benchmarks without files or network.
//!
//! The database follows the one-file format of thesis §3.3.2 as written by
//! `planet-core::format` (records with child references, written bottom-up,
//! roots' first LODs in the header), over a sphere with a smooth analytic
//! elevation and colour. [`FakeServer`] answers requests by slicing the byte
//! vector after a configurable latency in frames, honours cancellations, and
//! can corrupt chosen records once.

use planet_client::{FrameOutput, Outgoing};
use planet_core::codec::{ColourCodec, ElevationCodec};
use planet_core::cube::{sample_coord, FaceCoord};
use planet_core::format::{encode_record, ChildRef, Header, Tree, TreeInfo, SUPERBLOCK_LEN};
use planet_core::lod::{self, Rgb};
use planet_core::{BlockId, Datum, Face};
use std::collections::{HashMap, HashSet};

/// The test databases are exact (tests compare decoded samples with the
/// analytic ones): exact quantised elevation, lossless colour.
const ELEVATION_CODEC: ElevationCodec = ElevationCodec::Quantised { max_error: 0 };
const COLOUR_CODEC: ColourCodec = ColourCodec::Lossless;

/// Parameters of a synthetic database.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TestDbConfig {
    /// Sphere radius in metres.
    pub radius: f64,
    /// Elevation block width.
    pub elevation_width: usize,
    /// Deepest elevation level.
    pub elevation_max_level: u8,
    /// Colour block width and deepest level, if any.
    pub colour: Option<(usize, u8)>,
}

impl Default for TestDbConfig {
    fn default() -> Self {
        TestDbConfig {
            radius: 6_371_000.0,
            elevation_width: 8,
            elevation_max_level: 4,
            colour: Some((16, 3)),
        }
    }
}

/// A synthetic database: the bytes of a file and the exact samples of every
/// block.
#[derive(Debug, Clone)]
pub struct TestDb {
    /// The file: a zeroed superblock, then records (the header is separate).
    pub file: Vec<u8>,
    /// The header.
    pub header: Header,
    /// Full elevation grid of every block.
    pub elevation: HashMap<BlockId, Vec<i16>>,
    /// Full colour grid of every block.
    pub colour: HashMap<BlockId, Vec<Rgb>>,
    /// Record reference of every block, per tree.
    pub refs: HashMap<(Tree, BlockId), ChildRef>,
}

/// The analytic elevation (metres) at a unit direction.
pub fn elevation_at(d: [f64; 3]) -> f64 {
    1500.0 * (3.0 * d[0] + 1.0).sin() * (2.0 * d[1]).cos() + 800.0 * (5.0 * d[2]).sin()
}

fn colour_at(d: [f64; 3]) -> Rgb {
    let c = |v: f64| ((v * 0.5 + 0.5) * 255.0).round().clamp(0.0, 255.0) as u8;
    [
        c((4.0 * d[0]).sin()),
        c((3.0 * d[1] + d[2]).cos()),
        c((6.0 * d[2]).sin()),
    ]
}

fn elevation_grid(b: BlockId, w: usize) -> Vec<i16> {
    let n = (w as u64) << b.level;
    let mut g = Vec::with_capacity((w + 1) * (w + 1));
    for j in 0..=w as u64 {
        for i in 0..=w as u64 {
            let fc = FaceCoord {
                face: b.face,
                s: sample_coord(b.x as u64 * w as u64 + i, n),
                t: sample_coord(b.y as u64 * w as u64 + j, n),
            };
            g.push(elevation_at(fc.direction()).round() as i16);
        }
    }
    g
}

struct Builder {
    cfg: TestDbConfig,
    file: Vec<u8>,
    elevation: HashMap<BlockId, Vec<i16>>,
    colour: HashMap<BlockId, Vec<Rgb>>,
    refs: HashMap<(Tree, BlockId), ChildRef>,
}

impl Builder {
    fn append(&mut self, rec: Vec<u8>) -> (u64, u32) {
        let off = self.file.len() as u64;
        let size = rec.len() as u32;
        self.file.extend_from_slice(&rec);
        (off, size)
    }

    fn build_elevation(&mut self, b: BlockId) -> ChildRef {
        let w = self.cfg.elevation_width;
        let g = elevation_grid(b, w);
        let mut lo = g.iter().copied().min().unwrap_or(0) as f32;
        let mut hi = g.iter().copied().max().unwrap_or(0) as f32;
        let mut kids = vec![];
        if b.level < self.cfg.elevation_max_level {
            for c in b.children() {
                let r = self.build_elevation(c);
                lo = lo.min(r.min_elevation);
                hi = hi.max(r.max_elevation);
                kids.push(r);
            }
        }
        let rec = encode_record(Tree::Elevation, b, &kids, &ELEVATION_CODEC.encode(&g, w));
        let (offset, size) = self.append(rec);
        let r = ChildRef {
            offset,
            size,
            error: lod::elevation_lod_error(&g, w) as f32,
            // Analytic data between samples can exceed the sampled range.
            min_elevation: lo - 50.0,
            max_elevation: hi + 50.0,
        };
        self.elevation.insert(b, g);
        self.refs.insert((Tree::Elevation, b), r);
        r
    }

    fn build_colour(&mut self, b: BlockId, w: usize, max_level: u8) -> (ChildRef, Vec<Rgb>) {
        let mut kids = vec![];
        let full = if b.level < max_level {
            let mut full = vec![[0u8; 3]; w * w];
            for (k, c) in b.children().into_iter().enumerate() {
                let (r, cf) = self.build_colour(c, w, max_level);
                lod::merge_colour(&lod::colour_filter(&cf, w), w, k, &mut full);
                kids.push(r);
            }
            full
        } else {
            let n = (w as f64) * (1u64 << b.level) as f64;
            let mut full = Vec::with_capacity(w * w);
            for j in 0..w {
                for i in 0..w {
                    let fc = FaceCoord {
                        face: b.face,
                        s: (b.x as f64 * w as f64 + i as f64 + 0.5) / n,
                        t: (b.y as f64 * w as f64 + j as f64 + 0.5) / n,
                    };
                    full.push(colour_at(fc.direction()));
                }
            }
            full
        };
        let lod1 = lod::colour_filter(&full, w);
        let mut err = 0u8;
        for j in 0..w {
            for i in 0..w {
                let m = lod1[(j / 2) * (w / 2) + i / 2];
                for ch in 0..3 {
                    err = err.max(full[j * w + i][ch].abs_diff(m[ch]));
                }
            }
        }
        let rec = encode_record(
            Tree::Colour,
            b,
            &kids,
            &COLOUR_CODEC.encode(&full, &lod1, w, 0).0,
        );
        let (offset, size) = self.append(rec);
        let r = ChildRef {
            offset,
            size,
            error: err as f32,
            min_elevation: 0.0,
            max_elevation: 0.0,
        };
        self.colour.insert(b, full.clone());
        self.refs.insert((Tree::Colour, b), r);
        (r, full)
    }
}

impl TestDb {
    /// Build a database.
    pub fn build(cfg: TestDbConfig) -> TestDb {
        let mut b = Builder {
            cfg,
            file: vec![0u8; SUPERBLOCK_LEN],
            elevation: HashMap::new(),
            colour: HashMap::new(),
            refs: HashMap::new(),
        };
        let w = cfg.elevation_width;
        let mut roots = [ChildRef::default(); 6];
        let mut firsts: [Vec<i16>; 6] = Default::default();
        for f in Face::ALL {
            let id = BlockId::root(f);
            roots[f.index() as usize] = b.build_elevation(id);
            firsts[f.index() as usize] = lod::elevation_first_lod(&b.elevation[&id], w);
        }
        let colour = cfg.colour.map(|(cw, cl)| {
            let mut croots = [ChildRef::default(); 6];
            let mut cfirsts: [Vec<Rgb>; 6] = Default::default();
            for f in Face::ALL {
                let (r, full) = b.build_colour(BlockId::root(f), cw, cl);
                croots[f.index() as usize] = r;
                cfirsts[f.index() as usize] = lod::colour_filter(&full, cw);
            }
            TreeInfo {
                block_width: cw as u16,
                codec: COLOUR_CODEC,
                max_level: cl,
                root_records: croots,
                root_first_lods: cfirsts,
            }
        });
        let (lo, hi) = roots.iter().fold((f32::MAX, f32::MIN), |(lo, hi), r| {
            (lo.min(r.min_elevation), hi.max(r.max_elevation))
        });
        let header = Header {
            datum: Datum::Sphere { radius: cfg.radius },
            elevation_scale: 1.0,
            elevation_offset: 0.0,
            min_elevation: lo,
            max_elevation: hi,
            elevation: TreeInfo {
                block_width: w as u16,
                codec: ELEVATION_CODEC,
                max_level: cfg.elevation_max_level,
                root_records: roots,
                root_first_lods: firsts,
            },
            colour,
            description: "synthetic test sphere".into(),
        };
        TestDb {
            file: b.file,
            header,
            elevation: b.elevation,
            colour: b.colour,
            refs: b.refs,
        }
    }

    /// The bytes of a record, if the reference is inside the file.
    pub fn read(&self, r: &ChildRef) -> Option<Vec<u8>> {
        let start = usize::try_from(r.offset).ok()?;
        let end = start.checked_add(r.size as usize)?;
        self.file.get(start..end).map(<[u8]>::to_vec)
    }
}

/// A server that answers after `latency_frames` frames.
#[derive(Debug, Clone)]
pub struct FakeServer {
    /// Frames between a request and its response (0: delivered at once).
    pub latency_frames: u64,
    /// Record offsets to corrupt once (a byte flipped in the payload).
    pub corrupt_once: HashSet<u64>,
    pending: Vec<(u64, u64, ChildRef, Option<[f32; 4]>)>,
    now: u64,
    /// Every request ever sent, in order.
    pub log: Vec<Outgoing>,
}

impl FakeServer {
    /// A server with this latency.
    pub fn new(latency_frames: u64) -> FakeServer {
        FakeServer {
            latency_frames,
            corrupt_once: HashSet::new(),
            pending: vec![],
            now: 0,
            log: vec![],
        }
    }

    /// Take a frame's requests and cancellations.
    pub fn submit(&mut self, out: &FrameOutput) {
        let cancelled: HashSet<u64> = out.cancel.iter().copied().collect();
        self.pending.retain(|p| !cancelled.contains(&p.1));
        for s in &out.send {
            self.log.push(*s);
            self.pending
                .push((self.now + self.latency_frames, s.id, s.record, s.refs));
        }
    }

    /// Advance one frame; the responses due now.
    pub fn tick(&mut self, db: &TestDb) -> Vec<(u64, Vec<u8>)> {
        let now = self.now;
        self.now += 1;
        let (due, rest): (Vec<_>, Vec<_>) = self.pending.drain(..).partition(|p| p.0 <= now);
        self.pending = rest;
        due.into_iter()
            .filter_map(|(_, id, r, refs)| {
                let mut bytes = db.read(&r)?;
                // A `LodRefsAboveRequest`: the child tables that reach
                // their floors after the record, as planet-server answers it.
                let tables = refs.and_then(|floors| {
                    planet_core::format::child_tables_for(&bytes, None, Some(floors), |c| {
                        db.read(c)
                    })
                    .ok()
                });
                if self.corrupt_once.remove(&r.offset) {
                    let k = bytes.len() / 2;
                    bytes[k] ^= 0x5a;
                }
                bytes.extend(tables.unwrap_or_default());
                Some((id, bytes))
            })
            .collect()
    }

    /// Requests not yet answered.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }
}

/// Writes a small two-level database file at `path` (elevation tree only,
/// WGS84, block width `block_width`, elevations −5…5 m): per face a root
/// record with its four children as leaves, each payload `payload(face,
/// Some(child))` or `payload(face, None)` for the root, stored lz4. The
/// payloads are never decoded. Returns every record's `(offset, size)` in
/// file order (per face: the four children, then the root).
pub fn write_two_level_db(
    path: &std::path::Path,
    block_width: u16,
    description: &str,
    payload: impl Fn(usize, Option<usize>) -> Vec<u8>,
) -> std::io::Result<Vec<(u64, u32)>> {
    use planet_core::codec::Payload;
    use planet_core::format::DbWriter;
    let child_ref = |(offset, size): (u64, u32)| ChildRef {
        offset,
        size,
        error: 1.0,
        min_elevation: -5.0,
        max_elevation: 5.0,
    };
    let mut w = DbWriter::create(path)?;
    let mut all = Vec::new();
    let mut roots = [ChildRef::default(); 6];
    for (f, face) in Face::ALL.iter().enumerate() {
        let root = BlockId::root(*face);
        let mut kids = Vec::new();
        for (k, child) in root.children().iter().enumerate() {
            let raw = Payload::lz4(&payload(f, Some(k)));
            let at = w.append(&encode_record(Tree::Elevation, *child, &[], &raw))?;
            all.push(at);
            kids.push(child_ref(at));
        }
        let raw = Payload::lz4(&payload(f, None));
        let at = w.append(&encode_record(Tree::Elevation, root, &kids, &raw))?;
        all.push(at);
        roots[f] = child_ref(at);
    }
    let first_lod = (usize::from(block_width) / 2 + 1).pow(2);
    let header = Header {
        datum: Datum::WGS84,
        elevation_scale: 1.0,
        elevation_offset: 0.0,
        min_elevation: -5.0,
        max_elevation: 5.0,
        elevation: TreeInfo {
            block_width,
            // The payloads are never decoded: any codec id will do.
            codec: ElevationCodec::Legacy,
            max_level: 1,
            root_records: roots,
            root_first_lods: std::array::from_fn(|f| {
                (0..first_lod).map(|v| (v + f) as i16).collect()
            }),
        },
        colour: None,
        description: description.to_string(),
    };
    w.finish(&header)?;
    Ok(all)
}
