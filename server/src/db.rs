//! Validated database files, how record bytes are read from them, and their
//! reload.
//!
//! Each database is opened and validated (superblock and header, via
//! `planet-core`) **once**; all connections share it through an `Arc`.
//!
//! **Storage faults** (docs/SECURITY.md, "Storage faults"). Record bytes are
//! read according to [`StorageMode`]:
//! - `pread` (default): `read_exact_at` into a buffer per request. A file
//!   truncated in place, an I/O error or a stale network-filesystem handle
//!   is an `Err` for that request (`storage` on the wire,
//!   `planet_storage_errors_total`), never a signal.
//! - `mmap`: zero-copy slices of a read-only memory map. Before each
//!   request the file's current size is checked (`fstat`), which catches a
//!   truncation that happened before the request, but not one racing with
//!   the send (quinn reads the slice when it builds packets): such a race,
//!   or a device error under the map, raises SIGBUS and kills the process.
//! - `auto`: `pread` on network and FUSE filesystems (NFS, CIFS/SMB, Ceph,
//!   FUSE, 9P, AFS, Lustre, GPFS; `fstatfs`), `mmap` elsewhere.
//!
//!  A reload re-opens the path: if the file changed (device,
//! inode, mtime or length), the new file is validated and mapped for *new*
//! sessions, while open sessions keep their `Arc` to the old map (the old
//! inode stays alive until they close).
//!
//! **Operational rule:** database files are immutable. Publish a new version
//! by writing a new file and renaming it over the old path, never by
//! rewriting or truncating a served file in place: a truncated mapped file
//! makes reads of the missing pages raise SIGBUS and kill the process.

use std::fs::File;
use std::os::unix::fs::{FileExt, MetadataExt};
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use bytes::Bytes;
use memmap2::Mmap;
use planet_core::format::{peek_record_len, Superblock, SUPERBLOCK_LEN};
use planet_protocol::{ErrorCode, ErrorMsg};

use crate::config::StorageMode;

/// Why a database file cannot be served.
#[derive(Debug, thiserror::Error)]
pub enum DbError {
    /// The file cannot be opened, stat'ed or mapped.
    #[error("database {name:?} ({path}): {source}")]
    Io {
        /// Database name.
        name: String,
        /// File path.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is not a valid planet database (truncated, corrupt, foreign).
    #[error("database {name:?} ({path}) is invalid: {reason}")]
    Invalid {
        /// Database name.
        name: String,
        /// File path.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The superblock or the header does not decode.
    #[error("database {name:?} ({path}) is invalid: {part}: {source}")]
    Format {
        /// Database name.
        name: String,
        /// File path.
        path: PathBuf,
        /// `superblock` or `header`.
        part: &'static str,
        /// The decoder's error.
        source: planet_core::format::FormatError,
    },
}

/// Identity of a file on disk, to detect replacement.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileIdentity {
    dev: u64,
    ino: u64,
    mtime_ns: i128,
    len: u64,
}

impl FileIdentity {
    fn of(meta: &std::fs::Metadata) -> FileIdentity {
        FileIdentity {
            dev: meta.dev(),
            ino: meta.ino(),
            mtime_ns: i128::from(meta.mtime()) * 1_000_000_000 + i128::from(meta.mtime_nsec()),
            len: meta.len(),
        }
    }
}

/// `f_type` values (`statfs(2)`) of network and FUSE filesystems, where a
/// file may change or fail under a map without the local kernel knowing.
const REMOTE_FS_MAGIC: [(u32, &str); 10] = [
    (0x6969, "nfs"),
    (0xFF53_4D42, "cifs"),
    (0xFE53_4D42, "smb2"),
    (0x517B, "smb"),
    (0x00C3_6400, "ceph"),
    (0x6573_5546, "fuse"),
    (0x0102_1997, "9p"),
    (0x5346_414F, "afs"),
    (0x0BD0_0BD0, "lustre"),
    (0x4750_4653, "gpfs"),
];

/// The filesystem of `file`, if it is a network or FUSE one.
pub fn remote_filesystem(file: &File) -> Option<&'static str> {
    let st = rustix::fs::fstatfs(file).ok()?;
    // `f_type` is signed on some targets: compare the low 32 bits.
    let magic = st.f_type as u32;
    REMOTE_FS_MAGIC
        .iter()
        .find(|(m, _)| *m == magic)
        .map(|(_, n)| *n)
}

/// One validated version of a database file, read by `pread` or from a map.
pub struct MappedDb {
    /// Configured name.
    pub name: String,
    /// Path it was opened from.
    pub path: PathBuf,
    file: File,
    map: Option<Mmap>,
    len: u64,
    header: Vec<u8>,
    /// The checked superblock.
    pub superblock: Superblock,
    identity: FileIdentity,
}

impl std::fmt::Debug for MappedDb {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MappedDb")
            .field("name", &self.name)
            .field("path", &self.path)
            .field("len", &self.len)
            .field("mapped", &self.map.is_some())
            .field("superblock", &self.superblock)
            .finish()
    }
}

impl MappedDb {
    /// Opens and validates `path`, reading records by `pread`.
    pub fn open(name: &str, path: &Path) -> Result<MappedDb, DbError> {
        Self::open_with(name, path, StorageMode::Pread)
    }

    /// Opens and validates `path`, reading records as `mode` says.
    #[allow(unsafe_code)] // the read-only memory map below (SAFETY comment there)
    pub fn open_with(name: &str, path: &Path, mode: StorageMode) -> Result<MappedDb, DbError> {
        let io = |source| DbError::Io {
            name: name.to_string(),
            path: path.to_path_buf(),
            source,
        };
        let invalid = |reason: String| DbError::Invalid {
            name: name.to_string(),
            path: path.to_path_buf(),
            reason,
        };
        let undecodable = |part: &'static str| {
            move |source| DbError::Format {
                name: name.to_string(),
                path: path.to_path_buf(),
                part,
                source,
            }
        };
        let file = File::open(path).map_err(io)?;
        let meta = file.metadata().map_err(io)?;
        if !meta.is_file() {
            return Err(invalid("not a regular file".into()));
        }
        if meta.len() < SUPERBLOCK_LEN as u64 {
            return Err(invalid(format!(
                "truncated: {} bytes, a database has at least {SUPERBLOCK_LEN}",
                meta.len()
            )));
        }
        let use_map = match mode {
            StorageMode::Pread => false,
            StorageMode::Mmap => true,
            StorageMode::Auto => match remote_filesystem(&file) {
                Some(fs) => {
                    tracing::info!(database = name, path = %path.display(), filesystem = fs, "network filesystem: reading records with pread");
                    false
                }
                None => true,
            },
        };
        let len = meta.len();
        let map = if use_map {
            // SAFETY: the map is read-only. Its pages stay valid only while
            // the file is not truncated in place (module docs: `mmap` mode
            // trusts the deployment to publish by rename); every access is
            // a bounds-checked slice, preceded by an `fstat` size check.
            Some(unsafe { Mmap::map(&file) }.map_err(io)?)
        } else {
            None
        };
        // The one validation of a database's head (core), with the
        // protocol's Welcome limit on the header.
        let head =
            planet_core::format::read_validated_head(&file, len, planet_protocol::MAX_HEADER_LEN)
                .map_err(undecodable("superblock and header"))?;
        let (superblock, header) = (head.superblock, head.header_bytes);
        Ok(MappedDb {
            name: name.to_string(),
            path: path.to_path_buf(),
            file,
            map,
            len,
            header,
            superblock,
            identity: FileIdentity::of(&meta),
        })
    }

    /// File length (at open).
    pub fn len(&self) -> u64 {
        self.len
    }

    /// True for an empty file (never for a valid database).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Whether records are served from a memory map (`mmap` mode).
    pub fn is_mapped(&self) -> bool {
        self.map.is_some()
    }

    /// The stored header bytes (sent in `Welcome`), read at open.
    pub fn header_bytes(&self) -> &[u8] {
        &self.header
    }

    /// Reads `len` bytes at `offset`: a `pread`, or a zero-copy slice of the
    /// map after checking that the file still covers it. A file shorter
    /// than the range (truncated in place) or a failing read is an `Err`.
    pub fn read(self: &Arc<Self>, offset: u64, len: usize) -> std::io::Result<Bytes> {
        let end = offset
            .checked_add(len as u64)
            .filter(|&e| e <= self.len)
            .ok_or_else(|| std::io::Error::other("range outside the file"))?;
        if self.map.is_some() {
            let now = self.file.metadata()?.len();
            if now < end {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    format!(
                        "file truncated under the map: {now} bytes, {} at open",
                        self.len
                    ),
                ));
            }
            let slice = RecordSlice::new(Arc::clone(self), offset as usize, end as usize)
                .ok_or_else(|| std::io::Error::other("range outside the map"))?;
            return Ok(Bytes::from_owner(slice));
        }
        let mut buf = vec![0u8; len];
        self.file.read_exact_at(&mut buf, offset)?;
        Ok(Bytes::from(buf))
    }

    /// Offset where the records end (the header starts).
    pub fn records_end(&self) -> u64 {
        self.superblock.header_offset
    }

    /// Whether `size` bytes at `offset` are one whole record of this file
    /// (docs/PROTOCOL.md, "Requests"): inside the record area
    /// `[64, header_offset)` (else `out_of_range`), starting with a record
    /// prefix (else `not_a_record`) whose length is `size` (else
    /// `wrong_size`). Reads only the 8-byte prefix; a failing read is
    /// [`RequestCheck::Storage`]. A function of the file alone (the
    /// `db_open_request` fuzz target drives it with the open).
    pub fn check_request(self: &Arc<Self>, offset: u64, size: u32) -> Result<(), RequestCheck> {
        let refused = |code, reason: String| RequestCheck::Refused(ErrorMsg::new(code, reason));
        let end = offset.checked_add(u64::from(size));
        if offset < SUPERBLOCK_LEN as u64 || end.is_none_or(|e| e > self.records_end()) {
            return Err(refused(
                ErrorCode::OutOfRange,
                format!(
                    "{offset}+{size} is outside the record area [{SUPERBLOCK_LEN}, {})",
                    self.records_end()
                ),
            ));
        }
        if offset + 8 > self.records_end() {
            return Err(refused(
                ErrorCode::NotARecord,
                "no record prefix at offset".into(),
            ));
        }
        let prefix = self.read(offset, 8).map_err(RequestCheck::Storage)?;
        let len = peek_record_len(&prefix).map_err(|e| {
            refused(
                ErrorCode::NotARecord,
                format!("offset {offset} is not a record start: {e}"),
            )
        })?;
        if len != size {
            return Err(refused(
                ErrorCode::WrongSize,
                format!("record at {offset} is {len} bytes, not {size}"),
            ));
        }
        Ok(())
    }
}

/// Why [`MappedDb::check_request`] refuses a request.
#[derive(Debug, thiserror::Error)]
pub enum RequestCheck {
    /// Not a record of this file: the error reply to send.
    #[error("{0:?}")]
    Refused(ErrorMsg),
    /// The record prefix could not be read (truncated or failing storage).
    #[error("cannot read the record prefix: {0}")]
    Storage(#[source] std::io::Error),
}

/// A byte range of a mapped database, usable as a zero-copy `Bytes` owner.
pub struct RecordSlice {
    db: Arc<MappedDb>,
    start: usize,
    end: usize,
}

impl RecordSlice {
    /// A slice; the range must have been checked against the map.
    pub fn new(db: Arc<MappedDb>, start: usize, end: usize) -> Option<RecordSlice> {
        let map_len = db.map.as_ref()?.len();
        if start <= end && end <= map_len {
            Some(RecordSlice { db, start, end })
        } else {
            None
        }
    }
}

impl AsRef<[u8]> for RecordSlice {
    fn as_ref(&self) -> &[u8] {
        // `new` checked the range against the map, which never changes.
        self.db
            .map
            .as_ref()
            .and_then(|m| m.get(self.start..self.end))
            .unwrap_or(&[])
    }
}

/// The current version of one configured database.
#[derive(Debug)]
pub struct DbSlot {
    /// Configured name.
    pub name: String,
    /// Configured path.
    pub path: PathBuf,
    mode: StorageMode,
    current: RwLock<Arc<MappedDb>>,
}

/// What a reload did for one database.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ReloadOutcome {
    /// Same file: nothing to do.
    Unchanged,
    /// A new file was mapped for new sessions.
    Reloaded,
    /// The new file could not be opened or is invalid: the old one stays.
    Failed(String),
}

impl DbSlot {
    /// Opens the database for the first time.
    pub fn open(name: &str, path: &Path, mode: StorageMode) -> Result<DbSlot, DbError> {
        let db = MappedDb::open_with(name, path, mode)?;
        Ok(DbSlot {
            name: name.to_string(),
            path: path.to_path_buf(),
            mode,
            current: RwLock::new(Arc::new(db)),
        })
    }

    /// The version new sessions get.
    pub fn current(&self) -> Arc<MappedDb> {
        match self.current.read() {
            Ok(g) => Arc::clone(&g),
            Err(poisoned) => Arc::clone(&poisoned.into_inner()),
        }
    }

    /// Re-opens the path; maps it if the file changed.
    pub fn reload(&self) -> ReloadOutcome {
        let cur = self.current();
        match std::fs::metadata(&self.path) {
            Ok(meta) if FileIdentity::of(&meta) == cur.identity => return ReloadOutcome::Unchanged,
            Ok(_) => {}
            Err(e) => return ReloadOutcome::Failed(format!("{}: {e}", self.path.display())),
        }
        match MappedDb::open_with(&self.name, &self.path, self.mode) {
            Ok(db) => {
                let db = Arc::new(db);
                match self.current.write() {
                    Ok(mut g) => *g = db,
                    Err(poisoned) => *poisoned.into_inner() = db,
                }
                ReloadOutcome::Reloaded
            }
            Err(e) => ReloadOutcome::Failed(e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    /// The header travels whole in the Welcome: the format may not allow a
    /// header the protocol refuses, nor the other way round.
    #[test]
    fn format_and_protocol_agree_on_the_header_limit() {
        assert_eq!(
            planet_core::format::MAX_HEADER_LEN,
            planet_protocol::MAX_HEADER_LEN
        );
    }

    /// A `LodRefsRequest` response carries `encode_child_tables` (core) in a
    /// trailer whose length the client's decoder bounds (protocol).
    #[test]
    fn format_and_protocol_agree_on_the_child_tables_limit() {
        assert_eq!(
            planet_core::format::MAX_CHILD_TABLES_LEN,
            planet_protocol::MAX_REFS_TRAILER_LEN as usize
        );
    }
}
