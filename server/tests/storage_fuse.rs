//! Storage faults from a real failing filesystem: the served database lives
//! on a FUSE filesystem of this test (the `fuser` crate, the kernel's FUSE
//! driver) whose reads fail with `EIO` from a chosen offset on, the way a
//! dying disk or a network filesystem that lost its server fails. With
//! `storage = "auto"` the server must detect the FUSE mount and read by
//! `pread` (a memory map would turn the `EIO` into SIGBUS and kill this
//! process), answer `storage` for the records it cannot read, keep serving
//! the rest and the other database, and serve the records again once the
//! device recovers.
//!
//! Needs `/dev/fuse` and the right to mount (root or fusermount). Without
//! them it prints a note and passes, except under `PLANET_CI=1` or
//! `PLANET_REQUIRE_ALL=1`, where a skip fails.

mod common;

use std::ffi::OsStr;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, UNIX_EPOCH};

use common::*;
use fuser::{
    Errno, FileAttr, FileHandle, FileType, Filesystem, FopenFlags, INodeNo, LockOwner, MountOption,
    OpenFlags, ReplyAttr, ReplyData, ReplyDirectory, ReplyEntry, ReplyOpen, Request,
};
use planet_protocol::{ErrorCode, Hello};
use planet_server::{Server, StorageMode};

const FILE_INO: INodeNo = INodeNo(2);
const NAME: &str = "earth.planetdb";
const TTL: Duration = Duration::from_secs(3600);

/// A read-only filesystem with one file, `earth.planetdb`, whose reads
/// touching `[fail_from, ∞)` fail with `EIO`. Files are opened with direct
/// I/O, so every read reaches the filesystem (no page cache hides a fault).
struct FaultyFs {
    bytes: Vec<u8>,
    fail_from: Arc<AtomicU64>,
    failed_reads: Arc<AtomicU64>,
}

impl FaultyFs {
    fn attr(&self, ino: INodeNo) -> FileAttr {
        let file = ino == FILE_INO;
        FileAttr {
            ino,
            size: if file { self.bytes.len() as u64 } else { 0 },
            blocks: if file {
                self.bytes.len().div_ceil(512) as u64
            } else {
                0
            },
            atime: UNIX_EPOCH,
            mtime: UNIX_EPOCH,
            ctime: UNIX_EPOCH,
            crtime: UNIX_EPOCH,
            kind: if file {
                FileType::RegularFile
            } else {
                FileType::Directory
            },
            perm: if file { 0o444 } else { 0o555 },
            nlink: if file { 1 } else { 2 },
            uid: 0,
            gid: 0,
            rdev: 0,
            flags: 0,
            blksize: 4096,
        }
    }
}

impl Filesystem for FaultyFs {
    fn lookup(&self, _req: &Request, parent: INodeNo, name: &OsStr, reply: ReplyEntry) {
        if parent == INodeNo::ROOT && name == NAME {
            reply.entry(&TTL, &self.attr(FILE_INO), fuser::Generation(0));
        } else {
            reply.error(Errno::ENOENT);
        }
    }

    fn getattr(&self, _req: &Request, ino: INodeNo, _fh: Option<FileHandle>, reply: ReplyAttr) {
        if ino == FILE_INO || ino == INodeNo::ROOT {
            reply.attr(&TTL, &self.attr(ino));
        } else {
            reply.error(Errno::ENOENT);
        }
    }

    fn open(&self, _req: &Request, _ino: INodeNo, _flags: OpenFlags, reply: ReplyOpen) {
        reply.opened(FileHandle(0), FopenFlags::FOPEN_DIRECT_IO);
    }

    fn read(
        &self,
        _req: &Request,
        ino: INodeNo,
        _fh: FileHandle,
        offset: u64,
        size: u32,
        _flags: OpenFlags,
        _lock_owner: Option<LockOwner>,
        reply: ReplyData,
    ) {
        if ino != FILE_INO {
            reply.error(Errno::ENOENT);
            return;
        }
        let len = self.bytes.len() as u64;
        let start = offset.min(len);
        let end = offset.saturating_add(u64::from(size)).min(len);
        if end > self.fail_from.load(Ordering::SeqCst) {
            self.failed_reads.fetch_add(1, Ordering::SeqCst);
            reply.error(Errno::EIO);
            return;
        }
        reply.data(&self.bytes[start as usize..end as usize]);
    }

    fn readdir(
        &self,
        _req: &Request,
        ino: INodeNo,
        _fh: FileHandle,
        offset: u64,
        mut reply: ReplyDirectory,
    ) {
        if ino != INodeNo::ROOT {
            reply.error(Errno::ENOENT);
            return;
        }
        let entries = [
            (INodeNo::ROOT, FileType::Directory, "."),
            (INodeNo::ROOT, FileType::Directory, ".."),
            (FILE_INO, FileType::RegularFile, NAME),
        ];
        for (i, (ino, kind, name)) in entries.into_iter().enumerate().skip(offset as usize) {
            if reply.add(ino, (i + 1) as u64, kind, name) {
                break;
            }
        }
        reply.ok();
    }
}

/// Prints why the test cannot run here and returns, or fails in CI.
fn mount(dir: &Path, fs: FaultyFs) -> std::io::Result<fuser::BackgroundSession> {
    let mut cfg = fuser::Config::default();
    cfg.mount_options = vec![MountOption::RO, MountOption::FSName("planet-faulty".into())];
    fuser::spawn_mount(fs, dir, &cfg)
}

#[test]
fn a_failing_device_gives_storage_errors_then_recovers() {
    if !Path::new("/dev/fuse").exists() {
        planet_testkit::skip_or_fail("no /dev/fuse");
        return;
    }
    let rt = planet_testkit::runtime(2).expect("tokio runtime");
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, recs) = two_tenant_config(dir.path());
    let bytes = file_bytes(&dir.path().join(NAME));
    let fail_from = Arc::new(AtomicU64::new(u64::MAX));
    let failed_reads = Arc::new(AtomicU64::new(0));
    let mnt = dir.path().join("fuse");
    std::fs::create_dir(&mnt).unwrap();
    let session = match mount(
        &mnt,
        FaultyFs {
            bytes: bytes.clone(),
            fail_from: Arc::clone(&fail_from),
            failed_reads: Arc::clone(&failed_reads),
        },
    ) {
        Ok(s) => s,
        Err(e) => {
            planet_testkit::skip_or_fail(&format!("cannot mount a FUSE filesystem: {e}"));
            return;
        }
    };
    cfg.databases[0].path = mnt.join(NAME);
    cfg.storage = StorageMode::Auto;
    let h = rt
        .block_on(Server::start(cfg))
        .expect("the server opens the file over FUSE");
    rt.block_on(async {
        let (conn, _) = connect(&h, acme()).await.unwrap();
        let (mars_conn, _) = connect(&h, Hello::new("other", "t0ken", "mars"))
            .await
            .unwrap();
        let body_of = |off: u64, size: u32| &bytes[off as usize..(off + u64::from(size)) as usize];
        for (i, (off, size)) in recs.iter().enumerate() {
            assert_eq!(
                &conn.fetch(i as u64, *off, *size).await.unwrap()[..],
                body_of(*off, *size)
            );
        }
        // The device starts failing at the middle record.
        let cut = recs[recs.len() / 2].0;
        fail_from.store(cut, Ordering::SeqCst);
        let (mut ok, mut storage) = (0u32, 0u32);
        for (i, (off, size)) in recs.iter().enumerate() {
            match conn.fetch(100 + i as u64, *off, *size).await {
                Ok(body) => {
                    assert!(
                        off + u64::from(*size) <= cut,
                        "a record past the fault was served"
                    );
                    assert_eq!(&body[..], body_of(*off, *size));
                    ok += 1;
                }
                Err(e) if e.code() == Some(ErrorCode::Storage) => {
                    assert!(off + u64::from(*size) > cut, "{e:?}");
                    storage += 1;
                }
                Err(e) => panic!("{e:?}"),
            }
        }
        eprintln!(
            "failing device: {ok} records served, {storage} storage errors, {} failed reads",
            failed_reads.load(Ordering::SeqCst)
        );
        assert!(ok > 0 && storage > 0);
        assert!(failed_reads.load(Ordering::SeqCst) >= u64::from(storage));
        // The other database and the health endpoint are unaffected.
        let mars = file_bytes(&dir.path().join("mars.planetdb"));
        let first = planet_core::format::peek_record_len(&mars[64..]).unwrap();
        let body = mars_conn.fetch(1, 64, first).await.unwrap();
        assert_eq!(&body[..], &mars[64..64 + first as usize]);
        let (status, _) = http_get(h.metrics_addr().unwrap(), "/healthz").await;
        assert_eq!(status, 200);
        let text = scrape(&h).await;
        assert_eq!(
            metric(
                &text,
                "planet_storage_errors_total",
                &[("database", "earth")]
            ),
            f64::from(storage)
        );
        // The device recovers: every record is served again, on the same
        // connection.
        fail_from.store(u64::MAX, Ordering::SeqCst);
        for (i, (off, size)) in recs.iter().enumerate() {
            let body = conn.fetch(200 + i as u64, *off, *size).await.unwrap();
            assert_eq!(&body[..], body_of(*off, *size));
        }
        conn.close();
        mars_conn.close();
        h.shutdown().await;
    });
    session.umount_and_join().expect("unmount");
}
