//! Shared planet model and database format.
//!
//! Everything the preprocessor, the server and the client must agree on lives
//! here, each concept in one module:
//!
//! - [`cube`]: the six cube faces, their frames and edge table (Thesis §4.5.3,
//!   Table 4.1 as reconstructed in docs/REFERENCES.md), the adjusted gnomonic
//!   (equal-angle) sampling (thesis §4.5.2) and the forward/inverse maps between
//!   latitude/longitude and (face, s, t) (thesis Eq. 5.1, with its erratum).
//! - [`datum`]: reconstruction on the WGS84 ellipsoid or a sphere (thesis
//!   Eq. 4.2, with `e²` instead of `e`).
//! - [`camera`]: the one perspective camera (planet-centred `f64` metres)
//!   and its orthonormal basis.
//! - [`horizon`]: horizon-fitted near and far planes (thesis §4.5.4,
//!   Eq. 4.3, with its gap closed).
//! - [`block`]: block addressing (face, level, x, y), children, parents and
//!   neighbours inside a face and across cube edges (thesis §3.2, §4.3.2).
//! - [`lod`]: the interleaved LOD sample subsets of a block (Thesis §3.2,
//!   docs/REFERENCES.md) and the safe level difference between neighbours
//!   (thesis §4.3.3).
//! - [`codec`]: the payload codecs, chosen per tree in the header: the
//!   legacy lossless ones (predicted elevation residuals, thesis §4.4.4 PTM
//!   colour), error-bounded elevation and perceptual Haar colour.
//! - [`format`](mod@format): the one-file database: superblock, header and self-describing
//!   LOD records (thesis §3.3.2), byte by byte in `docs/FORMAT.md`.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod block;
pub mod camera;
pub mod codec;
pub mod cube;
pub mod datum;
pub mod format;
pub mod horizon;
pub mod lod;
pub mod pages;
pub mod pipe;

pub use block::{BlockId, Edge};
pub use cube::{Face, FaceCoord};
pub use datum::Datum;
