//! `LodRefsRequest` (docs/PROTOCOL.md §4.8) through the real server: the
//! record, then the child tables of its children, read from the children's
//! own records.

mod common;

use std::path::Path;
use std::time::Duration;

use common::*;
use planet_core::codec::{ElevationCodec, Payload};
use planet_core::format::{
    encode_record, parse_child_tables, parse_record, ChildRef, DbWriter, Header, Tree, TreeInfo,
    CHILD_TABLE_UNKNOWN,
};
use planet_core::{BlockId, Datum, Face};
use planet_protocol::{ErrorCode, ErrorFloors, RequestKind, StreamPriority, MAX_REFS_TRAILER_LEN};
use planet_server::{Server, ServerConfig};
use planet_session::net::{Connection, NetError, NetEvent, Session, SessionConfig};

/// Writes a three-level database over `path`: per face a root with four
/// children, of which children 0 and 1 have four leaf children each and
/// children 2 and 3 are leaves. Returns the offset of every root's child 0
/// record's last payload byte (a byte to corrupt), per face.
fn write_three_level_db(path: &Path) -> Vec<u64> {
    let child_ref = |(offset, size): (u64, u32), k: usize| ChildRef {
        offset,
        size,
        error: 1.0 + k as f32,
        min_elevation: -5.0 - k as f32,
        max_elevation: 5.0 + k as f32,
    };
    let payload = |seed: usize| Payload::lz4(&vec![seed as u8; 100 + seed % 37]);
    let mut w = DbWriter::create(path).unwrap();
    let mut roots = [ChildRef::default(); 6];
    let mut corrupt_at = Vec::new();
    for (f, face) in Face::ALL.iter().enumerate() {
        let root = BlockId::root(*face);
        let mut kids = Vec::new();
        for (k, child) in root.children().iter().enumerate() {
            let mut grandkids = Vec::new();
            if k < 2 {
                for (g, grandchild) in child.children().iter().enumerate() {
                    let rec = encode_record(
                        Tree::Elevation,
                        *grandchild,
                        &[],
                        &payload(f * 100 + k * 10 + g),
                    );
                    grandkids.push(child_ref(w.append(&rec).unwrap(), g));
                }
            }
            let rec = encode_record(Tree::Elevation, *child, &grandkids, &payload(f * 100 + k));
            let at = w.append(&rec).unwrap();
            if k == 0 {
                corrupt_at.push(at.0 + u64::from(at.1) - 5);
            }
            kids.push(child_ref(at, k));
        }
        let rec = encode_record(Tree::Elevation, root, &kids, &payload(f));
        roots[f] = child_ref(w.append(&rec).unwrap(), 0);
    }
    let block_width = 8u16;
    let first_lod = (usize::from(block_width) / 2 + 1).pow(2);
    let header = Header {
        datum: Datum::WGS84,
        elevation_scale: 1.0,
        elevation_offset: 0.0,
        min_elevation: -9.0,
        max_elevation: 9.0,
        elevation: TreeInfo {
            block_width,
            // The payloads are never decoded.
            codec: ElevationCodec::Legacy,
            max_level: 2,
            root_records: roots,
            root_first_lods: std::array::from_fn(|f| {
                (0..first_lod).map(|v| (v + f) as i16).collect()
            }),
        },
        colour: None,
        description: "three levels for LodRefsRequest".into(),
    };
    w.finish(&header).unwrap();
    corrupt_at
}

/// A server whose database `earth` is [`write_three_level_db`]; `corrupt`
/// flips a byte in every face's child 0 record first.
async fn three_level_server(dir: &Path, corrupt: bool) -> planet_server::ServerHandle {
    three_level_server_with(dir, corrupt, |_| {}).await
}

/// [`three_level_server`] with its configuration changed by `tweak`.
async fn three_level_server_with(
    dir: &Path,
    corrupt: bool,
    tweak: impl FnOnce(&mut ServerConfig),
) -> planet_server::ServerHandle {
    let (mut cfg, _) = two_tenant_config(dir);
    tweak(&mut cfg);
    let earth = dir.join("earth.planetdb");
    let corrupt_at = write_three_level_db(&earth);
    if corrupt {
        let mut bytes = std::fs::read(&earth).unwrap();
        for at in corrupt_at {
            bytes[at as usize] ^= 0x5a;
        }
        std::fs::write(&earth, bytes).unwrap();
    }
    Server::start(cfg).await.unwrap()
}

/// Connects to `h` as `acme` and decodes its database's header: the
/// connection, the database file's size and the header.
async fn open(h: &planet_server::ServerHandle) -> (Connection, u64, Header) {
    let (conn, welcome) = connect(h, acme()).await.unwrap();
    let header = Header::decode(&welcome.header, Some(welcome.file_size)).unwrap();
    (conn, welcome.file_size, header)
}

/// A three-level server configured by `tweak`, and a connection to it:
/// the server's directory (bind it for the server's life), the handle, the
/// connection, the file size and the header.
async fn served_with(
    tweak: impl FnOnce(&mut ServerConfig),
) -> (
    tempfile::TempDir,
    planet_server::ServerHandle,
    Connection,
    u64,
    Header,
) {
    let dir = tempfile::tempdir().unwrap();
    let h = three_level_server_with(dir.path(), false, tweak).await;
    let (conn, file_size, header) = open(&h).await;
    (dir, h, conn, file_size, header)
}

/// A `LodRefsAboveRequest` at floors of 0 m: every child table.
fn every_table_above() -> RequestKind {
    RequestKind::RecordAndRefsAbove(ErrorFloors::new([0.0; 4]).unwrap())
}

fn server_code(r: Result<Vec<u8>, NetError>) -> ErrorCode {
    match r {
        Err(NetError::Server(e)) => e.code,
        other => panic!("expected a server error head, got {other:?}"),
    }
}

/// `fetch_refs` of `r`, checked against `fetch` and against each child's
/// own record; returns the bytes received (record and trailer) and the
/// parsed tables.
async fn check_refs(
    conn: &Connection,
    file_size: u64,
    r: &ChildRef,
    id: &mut u64,
) -> (usize, Vec<Option<Vec<ChildRef>>>) {
    *id += 1;
    let with_refs = conn.fetch_refs(*id, r.offset, r.size).await.unwrap();
    *id += 1;
    let record = conn.fetch(*id, r.offset, r.size).await.unwrap();
    let size = r.size as usize;
    assert!(with_refs.len() >= size);
    assert!(with_refs.len() <= size + MAX_REFS_TRAILER_LEN as usize);
    assert_eq!(
        &with_refs[..size],
        &record[..],
        "the record part is the record"
    );
    let children = parse_record(&record, Some(file_size))
        .unwrap()
        .header
        .children;
    let trailer = &with_refs[size..];
    if children.is_empty() {
        assert!(trailer.is_empty(), "a leaf's response is the record alone");
    }
    let tables = parse_child_tables(trailer, children.len(), Some(file_size)).unwrap();
    for (k, (c, table)) in children.iter().zip(&tables).enumerate() {
        *id += 1;
        match conn.fetch(*id, c.offset, c.size).await {
            Ok(child) => {
                let own = parse_record(&child, Some(file_size))
                    .unwrap()
                    .header
                    .children;
                assert_eq!(table.as_ref(), Some(&own), "child {k} of {}", r.offset);
            }
            Err(e) => {
                assert_eq!(e.code(), Some(ErrorCode::CorruptRecord), "child {k}: {e}");
                assert_eq!(*table, None, "an unreadable child is unknown");
            }
        }
    }
    (with_refs.len(), tables)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refs_of_a_record_are_its_childrens_own_references() {
    let dir = tempfile::tempdir().unwrap();
    let h = three_level_server(dir.path(), false).await;
    let (conn, file_size, header) = open(&h).await;
    let mut id = 0;
    for root in &header.elevation.root_records {
        let (n, tables) = check_refs(&conn, file_size, root, &mut id).await;
        // Children 0 and 1 have four children, 2 and 3 are leaves: two
        // tables of 1 + 4 × 24 bytes, two of one byte.
        let counts: Vec<Option<usize>> = tables.iter().map(|t| t.as_ref().map(Vec::len)).collect();
        assert_eq!(counts, [Some(4), Some(4), Some(0), Some(0)]);
        assert_eq!(n, root.size as usize + 2 * (1 + 4 * 24) + 2);
        let record = conn.fetch(1000, root.offset, root.size).await.unwrap();
        let children = parse_record(&record, Some(file_size))
            .unwrap()
            .header
            .children;
        for (k, c) in children.iter().enumerate() {
            let (n, tables) = check_refs(&conn, file_size, c, &mut id).await;
            if k < 2 {
                // Four leaf children: four empty tables.
                assert_eq!(tables, vec![Some(vec![]); 4]);
                assert_eq!(n, c.size as usize + 4);
                // A grandchild, a leaf: the record alone.
                let g = tables_of(&conn, file_size, c).await[0];
                let (n, tables) = check_refs(&conn, file_size, &g, &mut id).await;
                assert!(tables.is_empty());
                assert_eq!(n, g.size as usize);
            } else {
                assert!(tables.is_empty());
                assert_eq!(n, c.size as usize);
            }
        }
    }
    conn.close();
    h.shutdown().await;
}

/// `LodRefsAboveRequest` (docs/PROTOCOL.md §4.9): a child's table of four
/// references comes only if their largest error reaches the child's
/// floor, and is unknown (one byte) otherwise; a leaf's empty table comes
/// whatever its floor.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tables_under_their_floors_are_left_out() {
    let dir = tempfile::tempdir().unwrap();
    let h = three_level_server(dir.path(), false).await;
    let (conn, file_size, header) = open(&h).await;
    let root = header.elevation.root_records[0];
    let size = root.size as usize;
    let all = conn.fetch_refs(1, root.offset, root.size).await.unwrap();
    let all_tables = parse_child_tables(&all[size..], 4, Some(file_size)).unwrap();
    // Children 0 and 1 hold four leaves of errors 1, 2, 3 and 4.
    let largest: Vec<Option<f32>> = all_tables
        .iter()
        .map(|t| {
            t.as_ref()
                .and_then(|t| t.iter().map(|r| r.error).reduce(f32::max))
        })
        .collect();
    assert_eq!(largest, [Some(4.0), Some(4.0), None, None]);
    let floors = ErrorFloors::new([4.0, 4.5, f32::INFINITY, 0.0]).unwrap();
    let some = conn
        .fetch_refs_above(2, root.offset, root.size, floors)
        .await
        .unwrap();
    assert_eq!(&some[..size], &all[..size], "the record part is the record");
    let tables = parse_child_tables(&some[size..], 4, Some(file_size)).unwrap();
    assert_eq!(tables[0], all_tables[0], "4 reaches 4");
    assert_eq!(tables[1], None, "4 is under 4.5");
    assert_eq!(tables[2..], [Some(vec![]), Some(vec![])], "leaves");
    assert_eq!(some.len(), all.len() - 4 * 24);
    assert_eq!(some[size + 1 + 4 * 24], CHILD_TABLE_UNKNOWN);
    // Floors of 0 are a LodRefsRequest.
    let zero = ErrorFloors::new([0.0; 4]).unwrap();
    let again = conn
        .fetch_refs_above(3, root.offset, root.size, zero)
        .await
        .unwrap();
    assert_eq!(again, all);
    assert!(!conn.table_floors_refused() && !conn.child_tables_refused());
    conn.close();
    h.shutdown().await;
}

/// A server with child tables turned off refuses 0x13 as it does 0x12: the
/// session asks again as a `LodRefsRequest`, then as a `LodRequest`, and
/// sends later ones as `LodRequest` straight away (docs/PROTOCOL.md §7).
/// With a `Priority` frame before the first, the session drops the
/// priority first (it cannot tell which frame was unknown), then falls
/// down the kinds: one refusal more, and no priorities on that connection.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refused_floors_fall_back_to_plain_requests() {
    for priority in [None, Some(StreamPriority { priority: 1 })] {
        let (_dir, h, conn, _, header) = served_with(|cfg| cfg.child_tables = false).await;
        let root = header.elevation.root_records[0];
        let kind = every_table_above();
        let got = conn
            .fetch_as(10, root.offset, root.size, kind, priority)
            .await
            .unwrap();
        let record = conn.fetch(11, root.offset, root.size).await.unwrap();
        assert_eq!(got, record, "the record alone");
        assert!(conn.table_floors_refused() && conn.child_tables_refused());
        assert_eq!(conn.priority_refused(), priority.is_some());
        let refused = invalid_once_ok(&h, 2.0).await;
        let expected = if priority.is_some() { 3.0 } else { 2.0 };
        assert_eq!(refused, expected, "(the priority), 0x13, then 0x12");
        let got = conn
            .fetch_as(12, root.offset, root.size, kind, priority)
            .await
            .unwrap();
        assert_eq!(got, record);
        let invalid = invalid_once_ok(&h, 3.0).await;
        assert_eq!(
            invalid, refused,
            "later requests are LodRequests from the start"
        );
        conn.close();
        h.shutdown().await;
    }
}

/// A request stream that begins with a `Priority` frame (docs/PROTOCOL.md
/// §4.10): a server with priorities answers it as any request; one with
/// them turned off, as a server that predates the frame (id 0,
/// `unknown_message`), and the session asks again without it, and sends
/// none on that connection from then on (§7).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_priority_frame_is_answered_or_dropped_where_refused() {
    let p = Some(StreamPriority { priority: 7 });
    for priorities in [true, false] {
        let (_dir, h, conn, _, header) = served_with(|cfg| cfg.stream_priority = priorities).await;
        let root = header.elevation.root_records[0];
        let record = conn.fetch(1, root.offset, root.size).await.unwrap();
        let got = conn
            .fetch_as(2, root.offset, root.size, RequestKind::Record, p)
            .await
            .unwrap();
        assert_eq!(got, record);
        // With child tables: the refs request keeps its kind either way.
        let got = conn
            .fetch_as(3, root.offset, root.size, every_table_above(), p)
            .await
            .unwrap();
        assert!(got.len() > record.len() && got.starts_with(&record));
        assert_eq!(conn.priority_refused(), !priorities, "{priorities}");
        assert!(!conn.table_floors_refused() && !conn.child_tables_refused());
        let invalid = invalid_once_ok(&h, 3.0).await;
        assert_eq!(
            invalid,
            if priorities { 0.0 } else { 1.0 },
            "one refusal, then requests without the frame ({priorities})"
        );
        conn.close();
        h.shutdown().await;
    }
}

/// The requests the server refused as invalid, once it has answered `ok`
/// of them.
async fn invalid_once_ok(h: &planet_server::ServerHandle, ok: f64) -> f64 {
    let text = wait_metrics(h, |t| {
        metric(t, "planet_requests_total", &[("outcome", "ok")]) >= ok
    })
    .await;
    metric(&text, "planet_requests_total", &[("outcome", "invalid")])
}

/// The child references of the record `r` (from the record itself).
async fn tables_of(conn: &Connection, file_size: u64, r: &ChildRef) -> Vec<ChildRef> {
    let record = conn.fetch(2000, r.offset, r.size).await.unwrap();
    parse_record(&record, Some(file_size))
        .unwrap()
        .header
        .children
}

/// A server with child tables turned off answers 0x12 as one that predates
/// it (id 0, `unknown_message`; docs/PROTOCOL.md §7): the session asks
/// again with `LodRequest`, every request in flight and every later one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_without_child_tables_gets_plain_requests() {
    let (_dir, h, conn, _, header) = served_with(|cfg| cfg.child_tables = false).await;
    let roots = header.elevation.root_records;
    assert!(!conn.child_tables_refused());
    // Six refs requests in flight when the first refusal comes back.
    let asked: Vec<_> = roots
        .iter()
        .enumerate()
        .map(|(i, r)| conn.fetch_refs(10 + i as u64, r.offset, r.size))
        .collect();
    for (f, r) in asked.into_iter().zip(&roots) {
        let got = f.await.unwrap();
        let record = conn.fetch(99, r.offset, r.size).await.unwrap();
        assert_eq!(got, record, "the record alone");
    }
    assert!(conn.child_tables_refused());
    let refused = invalid_once_ok(&h, 12.0).await;
    assert!((1.0..=6.0).contains(&refused), "{refused}");
    // Later requests go out as LodRequest straight away.
    let got = conn
        .fetch_refs(50, roots[0].offset, roots[0].size)
        .await
        .unwrap();
    assert_eq!(got.len(), roots[0].size as usize);
    let invalid = invalid_once_ok(&h, 13.0).await;
    assert_eq!(invalid, refused);
    conn.close();
    h.shutdown().await;
}

/// A refs request reserves its largest response in the tenant's bandwidth
/// bucket and gets back what its trailer did not use: with no wait
/// allowed, leaves asked with `LodRefsRequest` (empty trailers) pass as
/// long as their records fit, not their reservations.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_unused_trailer_is_refunded_to_the_bandwidth_bucket() {
    let (_dir, h, conn, file_size, header) = served_with(|cfg| {
        cfg.max_rate_wait = Duration::ZERO;
        cfg.tenants[0].max_bytes_per_second = 2 * u64::from(MAX_REFS_TRAILER_LEN);
    })
    .await;
    // A grandchild: a leaf, whose trailer is empty.
    let root = header.elevation.root_records[0];
    let child = conn.fetch(1, root.offset, root.size).await;
    let child = parse_record(&child.unwrap(), Some(file_size))
        .unwrap()
        .header
        .children[0];
    let leaf = tables_of(&conn, file_size, &child).await[0];
    // Wait for the bucket to refill (2 * 388 bytes a second).
    tokio::time::sleep(Duration::from_millis(1500)).await;
    // A full bucket holds 776 bytes: two reservations of size + 388 fit
    // and a third does not, unless each gets its unused 388 back; then the
    // n-th still fits while n * size <= 388.
    let n = (MAX_REFS_TRAILER_LEN / leaf.size).min(6) as u64;
    assert!(n >= 3, "leaf of {} bytes", leaf.size);
    for id in 10..10 + n {
        let got = conn.fetch_refs(id, leaf.offset, leaf.size).await;
        assert_eq!(
            got.map(|b| b.len()).ok(),
            Some(leaf.size as usize),
            "request {id}"
        );
    }
    conn.close();
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bytes_sent_count_the_trailer() {
    let dir = tempfile::tempdir().unwrap();
    let h = three_level_server(dir.path(), false).await;
    let (conn, _, header) = open(&h).await;
    let root = header.elevation.root_records[0];
    let bytes = conn.fetch_refs(1, root.offset, root.size).await.unwrap();
    assert_eq!(bytes.len(), root.size as usize + 2 * 97 + 2);
    let text = wait_metrics(&h, |t| {
        metric(t, "planet_requests_total", &[("outcome", "ok")]) >= 1.0
    })
    .await;
    assert_eq!(
        metric(&text, "planet_bytes_sent_total", &[]),
        bytes.len() as f64
    );
    // The record size histogram sees the record alone.
    assert_eq!(
        metric(&text, "planet_record_size_bytes_sum", &[]),
        f64::from(root.size)
    );
    conn.close();
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_child_failing_its_checksum_is_unknown_in_the_table() {
    let dir = tempfile::tempdir().unwrap();
    let h = three_level_server(dir.path(), true).await;
    let (conn, file_size, header) = open(&h).await;
    let mut id = 0;
    for root in &header.elevation.root_records {
        // `check_refs` expects `corrupt_record` for child 0 and `None` in
        // its table; the other tables are the children's own.
        let (n, tables) = check_refs(&conn, file_size, root, &mut id).await;
        let counts: Vec<Option<usize>> = tables.iter().map(|t| t.as_ref().map(Vec::len)).collect();
        assert_eq!(counts, [None, Some(4), Some(0), Some(0)]);
        assert_eq!(n, root.size as usize + 1 + 97 + 2);
        let bytes = conn.fetch_refs(500, root.offset, root.size).await.unwrap();
        assert_eq!(bytes[root.size as usize], CHILD_TABLE_UNKNOWN);
    }
    conn.close();
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_refs_requests_get_the_codes_of_lod_requests() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    let file = file_bytes(&dir.path().join("earth.planetdb"));
    let h = Server::start(cfg).await.unwrap();
    let (conn, welcome) = connect(&h, acme()).await.unwrap();
    // recs: per face four leaves, then the root.
    let (off, size) = recs[0];
    let file_size = welcome.file_size;
    let cases: Vec<(u64, u32, ErrorCode)> = vec![
        (file_size + 10, 100, ErrorCode::OutOfRange),
        (0, 64, ErrorCode::OutOfRange),
        (off + 7, size, ErrorCode::NotARecord),
        (off, size + 1, ErrorCode::WrongSize),
        (off, 0, ErrorCode::WrongSize),
        (off, 17 * 1024 * 1024, ErrorCode::RecordTooLarge),
    ];
    for (i, (o, s, code)) in cases.iter().enumerate() {
        let id = 100 + i as u64;
        assert_eq!(server_code(conn.fetch(id, *o, *s).await), *code, "case {i}");
        assert_eq!(
            server_code(conn.fetch_refs(id, *o, *s).await),
            *code,
            "refs case {i}: offset {o} size {s}"
        );
    }
    // A leaf: exactly its record, as a LodRequest gets it.
    let leaf = conn.fetch_refs(1, off, size).await.unwrap();
    assert_eq!(&leaf[..], &file[off as usize..off as usize + size as usize]);
    // A root of leaves: four empty tables.
    let (root_off, root_size) = recs[4];
    let root = conn.fetch_refs(2, root_off, root_size).await.unwrap();
    assert_eq!(root.len(), root_size as usize + 4);
    assert_eq!(&root[root_size as usize..], &[0, 0, 0, 0]);
    conn.close();
    h.shutdown().await;
}

#[test]
fn a_session_delivers_the_trailer_of_request_refs() {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let h = rt.block_on(three_level_server(dir.path(), false));
    let session = Session::spawn(
        rt.handle(),
        SessionConfig::new(h.local_addr(), "localhost", tls_for(&h), acme()),
    );
    let wait_for = |pred: &dyn Fn(&NetEvent) -> bool| -> NetEvent {
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while std::time::Instant::now() < deadline {
            if let Some(ev) = session.wait_event(Duration::from_millis(100)) {
                if pred(&ev) {
                    return ev;
                }
            }
        }
        panic!("event not received");
    };
    let NetEvent::Connected(welcome) = wait_for(&|e| matches!(e, NetEvent::Connected(_))) else {
        unreachable!()
    };
    let header = Header::decode(&welcome.header, Some(welcome.file_size)).unwrap();
    let root = header.elevation.root_records[2];
    session.request_refs(1, root.offset, root.size);
    session.request(2, root.offset, root.size);
    let mut got = std::collections::HashMap::new();
    while got.len() < 2 {
        match wait_for(&|e| matches!(e, NetEvent::Record { .. } | NetEvent::Failed { .. })) {
            NetEvent::Record { id, bytes } => {
                got.insert(id, bytes);
            }
            other => panic!("{other:?}"),
        }
    }
    let size = root.size as usize;
    assert_eq!(got[&2].len(), size);
    assert_eq!(got[&1].len(), size + 2 * 97 + 2);
    assert_eq!(got[&1][..size], got[&2][..]);
    let children = parse_record(&got[&2], Some(welcome.file_size))
        .unwrap()
        .header
        .children;
    let tables = parse_child_tables(&got[&1][size..], 4, Some(welcome.file_size)).unwrap();
    assert_eq!(children.len(), tables.len());
    session.close();
    rt.block_on(h.shutdown());
}

/// The example of docs/PROTOCOL.md §4.8 is what the code writes.
#[test]
fn the_protocol_doc_example_is_the_code() {
    use planet_core::format::encode_child_tables;
    use planet_protocol::ResponseHead;
    let doc = include_str!("../../docs/PROTOCOL.md");
    let section = doc
        .split("### 4.8 `LodRefsRequest` (0x12)")
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .expect("§4.8 in docs/PROTOCOL.md");
    let lines: Vec<String> = section
        .lines()
        .map(|l| l.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect();
    let shown = |bytes: &[u8]| {
        let hex: Vec<String> = bytes.iter().map(|b| format!("{b:02x}")).collect();
        let hex = hex.join(" ");
        assert!(
            lines.contains(&hex),
            "docs/PROTOCOL.md §4.8 must show the line {hex}"
        );
    };
    let r = ChildRef {
        offset: 4096,
        size: 200,
        error: 1.5,
        min_elevation: -3.0,
        max_elevation: 9.0,
    };
    let trailer = encode_child_tables(&[Some(vec![r; 4]), Some(vec![]), None, Some(vec![])]);
    assert_eq!(trailer.len(), 100);
    assert_eq!(trailer[0], 4);
    assert_eq!(trailer[97..], [0x00, CHILD_TABLE_UNKNOWN, 0x00]);
    shown(&trailer[1..25]);
    assert_eq!(
        parse_child_tables(&trailer, 4, None).unwrap(),
        [Some(vec![r; 4]), Some(vec![]), None, Some(vec![])]
    );
    shown(
        &ResponseHead::ok(7, 4096 + trailer.len() as u32)
            .encode_frame()
            .unwrap(),
    );
}
