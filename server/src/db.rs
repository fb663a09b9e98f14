//! Memory-mapped, validated database files and their reload.
//!
//! Each database is opened, validated (superblock and header, via
//! `planet-core`) and memory-mapped **once**; all connections share the map
//! through an `Arc`. A reload re-opens the path: if the file changed (device,
//! inode, mtime or length), the new file is validated and mapped for *new*
//! sessions, while open sessions keep their `Arc` to the old map (the old
//! inode stays alive until they close).
//!
//! **Operational rule:** database files are immutable. Publish a new version
//! by writing a new file and renaming it over the old path, never by
//! rewriting or truncating a served file in place: a truncated mapped file
//! makes reads of the missing pages raise SIGBUS and kill the process.

use std::fs::File;
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use memmap2::Mmap;
use planet_core::format::{Header, Superblock, SUPERBLOCK_LEN};

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

/// One validated, mapped version of a database file.
pub struct MappedDb {
    /// Configured name.
    pub name: String,
    /// Path it was opened from.
    pub path: PathBuf,
    map: Mmap,
    /// The checked superblock.
    pub superblock: Superblock,
    identity: FileIdentity,
}

impl std::fmt::Debug for MappedDb {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MappedDb")
            .field("name", &self.name)
            .field("path", &self.path)
            .field("len", &self.map.len())
            .field("superblock", &self.superblock)
            .finish()
    }
}

impl MappedDb {
    /// Opens, maps and validates `path`.
    pub fn open(name: &str, path: &Path) -> Result<MappedDb, DbError> {
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
        // SAFETY: the map is read-only and the file is treated as immutable
        // (deployment rule: replace by rename, never modify in place; see the
        // module docs). All accesses are bounds-checked slices of the map,
        // whose length is fixed at map time.
        let map = unsafe { Mmap::map(&file) }.map_err(io)?;
        let len = map.len() as u64;
        let superblock = Superblock::decode(&map[..SUPERBLOCK_LEN])
            .map_err(|e| invalid(format!("superblock: {e}")))?;
        if superblock.file_len != len {
            return Err(invalid(format!(
                "truncated or extended: superblock says {} bytes, file has {len}",
                superblock.file_len
            )));
        }
        if superblock.header_len as usize > planet_protocol::MAX_HEADER_LEN {
            return Err(invalid(format!(
                "header of {} bytes exceeds the protocol limit of {}",
                superblock.header_len,
                planet_protocol::MAX_HEADER_LEN
            )));
        }
        let start = superblock.header_offset as usize;
        let end = start + superblock.header_len as usize;
        let header_bytes = map
            .get(start..end)
            .ok_or_else(|| invalid("header outside the file".into()))?;
        Header::decode(header_bytes, Some(len)).map_err(|e| invalid(format!("header: {e}")))?;
        Ok(MappedDb {
            name: name.to_string(),
            path: path.to_path_buf(),
            map,
            superblock,
            identity: FileIdentity::of(&meta),
        })
    }

    /// The whole file.
    pub fn bytes(&self) -> &[u8] {
        &self.map
    }

    /// File length.
    pub fn len(&self) -> u64 {
        self.map.len() as u64
    }

    /// True for an empty map (never for a valid database).
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// The stored header bytes (sent in `Welcome`).
    pub fn header_bytes(&self) -> &[u8] {
        let start = self.superblock.header_offset as usize;
        &self.map[start..start + self.superblock.header_len as usize]
    }

    /// Offset where the records end (the header starts).
    pub fn records_end(&self) -> u64 {
        self.superblock.header_offset
    }
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
        if start <= end && end <= db.map.len() {
            Some(RecordSlice { db, start, end })
        } else {
            None
        }
    }
}

impl AsRef<[u8]> for RecordSlice {
    fn as_ref(&self) -> &[u8] {
        &self.db.map[self.start..self.end]
    }
}

/// The current version of one configured database.
#[derive(Debug)]
pub struct DbSlot {
    /// Configured name.
    pub name: String,
    /// Configured path.
    pub path: PathBuf,
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
    pub fn open(name: &str, path: &Path) -> Result<DbSlot, DbError> {
        let db = MappedDb::open(name, path)?;
        Ok(DbSlot {
            name: name.to_string(),
            path: path.to_path_buf(),
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
        match MappedDb::open(&self.name, &self.path) {
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
