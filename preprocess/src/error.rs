//! Typed errors of the preprocessor library.

use planet_core::codec::CodecError;
use planet_core::format::FormatError;
use planet_core::BlockId;
use std::path::PathBuf;
use thiserror::Error;

/// Errors reading a GeoTIFF source.
#[derive(Debug, Error)]
pub enum GeoError {
    /// The file could not be opened (missing, permissions).
    #[error("cannot open {path}")]
    Open {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The TIFF decoder failed.
    #[error("{path}: TIFF error: {msg}")]
    Tiff {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        msg: String,
    },
    /// The raster's CRS cannot be read or used.
    #[error("{path}: unsupported CRS: {what}")]
    WrongCrs {
        /// The file.
        path: PathBuf,
        /// What was found.
        what: String,
    },
    /// The sample type is not int16, uint16, float32 (elevation) or RGB8/grey8.
    #[error("{path}: unsupported sample type: {what}")]
    UnsupportedSampleType {
        /// The file.
        path: PathBuf,
        /// What was found.
        what: String,
    },
    /// Georeferencing tags are missing or malformed.
    #[error("{path}: missing georeference: {what}")]
    Georeference {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
    /// Two inputs lie on different bodies or datums.
    #[error("{first} is on {first_datum} but {second} is on {second_datum}: one build takes inputs on one surface")]
    MixedDatums {
        /// The first input.
        first: PathBuf,
        /// Its surface.
        first_datum: String,
        /// The input that differs.
        second: PathBuf,
        /// Its surface.
        second_datum: String,
    },
    /// An elevation source was given where colour is needed or vice versa.
    #[error("{path}: {what}")]
    Role {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
}

/// Errors of a build.
#[derive(Debug, Error)]
pub enum BuildError {
    /// A source could not be read.
    #[error(transparent)]
    Source(#[from] GeoError),
    /// Writing the database failed.
    #[error("writing {path}: {msg}")]
    Write {
        /// The database being written.
        path: PathBuf,
        /// What happened (disk full is named as such).
        msg: String,
    },
    /// Invalid options.
    #[error("invalid options: {0}")]
    Options(String),
    /// The worker thread pool cannot be built.
    #[error("thread pool: {0}")]
    ThreadPool(#[from] rayon::ThreadPoolBuildError),
    /// The exact first pass of an in-loop build cannot be read back.
    #[error("reading back the exact pass {path}")]
    ExactPass {
        /// The first pass's file.
        path: PathBuf,
        /// What was wrong.
        #[source]
        source: planet_core::format::FormatError,
    },
}

impl BuildError {
    /// Map an I/O error while writing `path`, naming a full disk clearly.
    pub fn write(path: &std::path::Path, e: std::io::Error) -> BuildError {
        let msg = if e.kind() == std::io::ErrorKind::StorageFull || e.raw_os_error() == Some(28) {
            format!("disk full (no space left on device): {e}")
        } else {
            e.to_string()
        };
        BuildError::Write {
            path: path.to_path_buf(),
            msg,
        }
    }
}

/// A database that fails verification, reading or sampling.
#[derive(Debug, Error)]
pub enum DbError {
    /// The file could not be opened or its superblock/header is bad.
    #[error("cannot open database {path}")]
    Open {
        /// The file.
        path: PathBuf,
        /// Why.
        source: FormatError,
    },
    /// A bad byte range: the first offset found bad and why.
    #[error("corrupt database at offset {offset}: {reason}")]
    Corrupt {
        /// File offset of the bad record or gap.
        offset: u64,
        /// Why it is bad.
        reason: String,
    },
    /// A record cannot be read, parsed or decoded.
    #[error("corrupt database at offset {offset}: {source}")]
    Record {
        /// File offset of the record.
        offset: u64,
        /// Why.
        source: RecordError,
    },
    /// The file cannot be opened again for the linear scan.
    #[error("corrupt database at offset 0: reopen: {source}")]
    Reopen {
        /// The I/O error.
        source: std::io::Error,
    },
    /// Verifying against the sources: the source cannot give a leaf.
    #[error("corrupt database at offset {offset}: source of {block:?}: {source}")]
    Source {
        /// File offset of the leaf's record.
        offset: u64,
        /// The leaf.
        block: BlockId,
        /// The source's error.
        source: Box<BuildError>,
    },
    /// The point asked for is invalid.
    #[error("invalid query: {0}")]
    Query(String),
}

/// Why a record of a database (or the bytes at an offset) is bad.
#[derive(Debug, Error)]
pub enum RecordError {
    /// Reading failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The record does not parse or check.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The payload does not decode.
    #[error(transparent)]
    Codec(#[from] CodecError),
}
