//! Byte-exact wire format checks. These pin the encoding documented in
//! `docs/PROTOCOL.md` (the hex there is copied from here), so that a future
//! replacement of bincode can be verified to produce identical bytes.

use planet_protocol::*;

/// Parses whitespace-separated hex bytes; `"s:TEXT"` tokens are ASCII text.
fn hex(spec: &str) -> Vec<u8> {
    let mut out = Vec::new();
    for tok in spec.split_whitespace() {
        if let Some(text) = tok.strip_prefix("s:") {
            out.extend_from_slice(text.as_bytes());
        } else {
            out.push(u8::from_str_radix(tok, 16).expect("hex byte"));
        }
    }
    out
}

fn assert_wire(msg: Message, expected: &str) {
    let expected = hex(expected);
    let bytes = msg.encode_frame().expect("encode");
    assert_eq!(bytes, expected, "encoding of {msg:?}");
    let (decoded, used) = decode_frame(&expected).expect("decode").expect("complete");
    assert_eq!(used, expected.len());
    assert_eq!(decoded, msg);
}

#[test]
fn hello_bytes() {
    let hello = Hello {
        version: 1,
        tenant: "acme".into(),
        token: "s3cr3t".into(),
        database: "earth".into(),
    };
    // Also spelled out as plain hex, exactly as in docs/PROTOCOL.md.
    let doc_hex = "2a 00 00 00 01 01 00 04 00 00 00 00 00 00 00 61 63 6d 65 \
                   06 00 00 00 00 00 00 00 73 33 63 72 33 74 \
                   05 00 00 00 00 00 00 00 65 61 72 74 68";
    assert_eq!(hello.encode_frame().unwrap(), hex(doc_hex));
    assert_eq!(hex(doc_hex).len(), 46);
    assert_wire(
        hello.into(),
        "2a 00 00 00  01  01 00 \
         04 00 00 00 00 00 00 00 s:acme \
         06 00 00 00 00 00 00 00 s:s3cr3t \
         05 00 00 00 00 00 00 00 s:earth",
    );
}

#[test]
fn welcome_bytes() {
    let welcome = Welcome {
        version: 1,
        database: "earth".into(),
        file_size: 1_000_000,
        header: vec![0xaa, 0xbb],
        limits: Limits {
            max_in_flight: 64,
            max_record_size: 1 << 20,
            max_bytes_per_second: 0,
            idle_timeout_ms: 30_000,
        },
    };
    assert_wire(
        welcome.into(),
        "36 00 00 00  02  01 00 \
         05 00 00 00 00 00 00 00 s:earth \
         40 42 0f 00 00 00 00 00 \
         02 00 00 00 00 00 00 00 aa bb \
         40 00 00 00  00 00 10 00  00 00 00 00 00 00 00 00  30 75 00 00",
    );
}

#[test]
fn lod_request_bytes() {
    let req = LodRequest {
        id: 7,
        offset: 0x0102_0304_0506_0708,
        size: 4096,
    };
    assert_wire(
        req.into(),
        "15 00 00 00  10  07 00 00 00 00 00 00 00  08 07 06 05 04 03 02 01  00 10 00 00",
    );
    assert_eq!(req.encode_frame().unwrap().len(), LOD_REQUEST_FRAME_LEN);
}

#[test]
fn lod_refs_request_bytes() {
    let req = LodRequest {
        id: 7,
        offset: 0x0102_0304_0506_0708,
        size: 4096,
    };
    // The LodRequest body under type byte 0x12.
    let expected = "15 00 00 00  12  07 00 00 00 00 00 00 00  08 07 06 05 04 03 02 01  00 10 00 00";
    assert_wire(Message::LodRefsRequest(req), expected);
    let bytes = req.encode_frame_as(RequestKind::RecordAndRefs).unwrap();
    assert_eq!(bytes, hex(expected));
    assert_eq!(bytes.len(), LOD_REQUEST_FRAME_LEN);
    assert_eq!(
        RequestKind::RecordAndRefs
            .message(req)
            .encode_frame()
            .unwrap(),
        bytes
    );
    // The plain kind is the LodRequest frame, byte for byte.
    assert_eq!(
        req.encode_frame_as(RequestKind::Record).unwrap(),
        req.encode_frame().unwrap()
    );
    assert_eq!(
        MessageType::from_u8(0x12),
        Some(MessageType::LodRefsRequest)
    );
    assert_eq!(MessageType::LodRefsRequest.as_str(), "lod_refs_request");
    assert_eq!(
        decode_any_request_stream(&bytes),
        Ok((req, RequestKind::RecordAndRefs))
    );
}

#[test]
fn response_head_bytes() {
    let ok = ResponseHead::ok(7, 4096);
    assert_wire(
        ok.clone().into(),
        "11 00 00 00  11  07 00 00 00 00 00 00 00  00 00 00 00  00 10 00 00",
    );
    assert_eq!(ok.encode_frame().unwrap().len(), RESPONSE_HEAD_OK_FRAME_LEN);

    let err = ResponseHead::error(7, ErrorMsg::new(ErrorCode::OutOfRange, "bad"));
    assert_wire(
        err.into(),
        "1e 00 00 00  11  07 00 00 00 00 00 00 00  01 00 00 00  09 00 \
         03 00 00 00 00 00 00 00 s:bad  00 00 00 00",
    );
}

#[test]
fn small_control_message_bytes() {
    assert_wire(
        ErrorMsg::new(ErrorCode::Unauthorized, "bad token").into(),
        "14 00 00 00  03  02 00  09 00 00 00 00 00 00 00 62 61 64 20 74 6f 6b 65 6e",
    );
    assert_wire(
        Goodbye {
            reason: ErrorCode::ShuttingDown,
        }
        .into(),
        "03 00 00 00  04  12 00",
    );
    assert_wire(
        Cancel { id: 7 }.into(),
        "09 00 00 00  05  07 00 00 00 00 00 00 00",
    );
}

#[test]
fn constants() {
    assert_eq!(PROTOCOL_VERSION, 1);
    assert_eq!(ALPN, b"planet/1");
    assert_eq!(MAX_FRAME_LEN, 65536);
    assert_eq!(LOD_REQUEST_FRAME_LEN, 25);
    assert_eq!(RESPONSE_HEAD_OK_FRAME_LEN, 21);
    assert_eq!(MAX_REFS_TRAILER_LEN, 388);
    assert_eq!(RequestKind::RecordAndRefs.max_trailer_len(), 388);
    assert_eq!(RequestKind::Record.max_trailer_len(), 0);
    assert_eq!(quic::STREAM_CANCELLED, 17);
}

#[test]
fn protocol_doc_shows_the_hello_bytes() {
    let hello = Hello {
        version: 1,
        tenant: "acme".into(),
        token: "s3cr3t".into(),
        database: "earth".into(),
    };
    let hex: String = hello
        .encode_frame()
        .unwrap()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let doc = include_str!("../../docs/PROTOCOL.md");
    assert!(
        doc.lines().any(|l| l.trim() == hex),
        "docs/PROTOCOL.md must contain the Hello example as the line {hex}"
    );
}

const REFS_ABOVE_BYTES: &str = "25 00 00 00  13  07 00 00 00 00 00 00 00  08 07 06 05 04 03 02 01  00 10 00 00  00 00 00 00  00 00 20 40  00 00 80 7f  00 00 80 3f";

fn refs_above_example() -> (LodRequest, ErrorFloors) {
    let req = LodRequest {
        id: 7,
        offset: 0x0102_0304_0506_0708,
        size: 4096,
    };
    let floors = ErrorFloors::new([0.0, 2.5, f32::INFINITY, 1.0]).expect("valid floors");
    (req, floors)
}

#[test]
fn lod_refs_above_request_bytes() {
    let (req, floors) = refs_above_example();
    // The LodRequest body, then the four floors as f32 LE, under 0x13.
    let kind = RequestKind::RecordAndRefsAbove(floors);
    assert_wire(
        Message::LodRefsAboveRequest(LodRefsAboveRequest::new(req, floors)),
        REFS_ABOVE_BYTES,
    );
    let bytes = req.encode_frame_as(kind).unwrap();
    assert_eq!(bytes, hex(REFS_ABOVE_BYTES));
    assert_eq!(bytes.len(), LOD_REFS_ABOVE_REQUEST_FRAME_LEN);
    assert_eq!(MAX_REQUEST_FRAME_LEN, 41);
    assert_eq!(floors.get(), [0.0, 2.5, f32::INFINITY, 1.0]);
    assert_eq!(
        MessageType::from_u8(0x13),
        Some(MessageType::LodRefsAboveRequest)
    );
    assert_eq!(
        MessageType::LodRefsAboveRequest.as_str(),
        "lod_refs_above_request"
    );
    assert_eq!(decode_any_request_stream(&bytes), Ok((req, kind)));
    assert_eq!(kind.max_trailer_len(), MAX_REFS_TRAILER_LEN);
    assert_eq!(kind.fallback(), Some(RequestKind::RecordAndRefs));
    assert_eq!(
        RequestKind::RecordAndRefs.fallback(),
        Some(RequestKind::Record)
    );
    assert_eq!(RequestKind::Record.fallback(), None);
    // A server that serves only LodRequest refuses it as it refuses 0x12.
    assert_eq!(
        decode_request_stream(&bytes),
        Err(ProtocolError::UnexpectedMessage {
            got: MessageType::LodRefsAboveRequest,
            context: "on a request stream (expected lod_request)",
        })
    );
}

#[test]
fn a_floor_that_is_nan_or_negative_is_refused_both_ways() {
    for bad in [f32::NAN, -1.0, f32::NEG_INFINITY] {
        assert!(ErrorFloors::new([0.0, bad, 1.0, 1.0]).is_err(), "{bad}");
        // Decoded from the wire: the frame is malformed (an invalid field).
        let mut bytes = hex(REFS_ABOVE_BYTES);
        let at = LOD_REQUEST_FRAME_LEN + 4;
        bytes[at..at + 4].copy_from_slice(&bad.to_le_bytes());
        let err = decode_any_request_stream(&bytes).expect_err("a bad floor decodes");
        assert!(
            matches!(err, ProtocolError::InvalidField { field, .. } if field == "lod_refs_above_request.floors"),
            "{err:?}"
        );
        assert_eq!(err.code(), ErrorCode::Malformed);
    }
    // +∞ and 0 (and −0) are floors.
    assert!(ErrorFloors::new([0.0, -0.0, f32::INFINITY, f32::MAX]).is_ok());
}

/// Asserts that the section of docs/PROTOCOL.md under `heading` shows
/// `bytes` on one line, as the document spells frames: single spaces
/// between bytes, double spaces between fields.
fn assert_doc_shows(heading: &str, bytes: &[u8]) {
    let doc = include_str!("../../docs/PROTOCOL.md");
    let section = doc
        .split(heading)
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .unwrap_or_else(|| panic!("{heading} in docs/PROTOCOL.md"));
    let normalised: Vec<String> = section
        .lines()
        .map(|l| l.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect();
    let want: Vec<String> = bytes.iter().map(|b| format!("{b:02x}")).collect();
    assert!(
        normalised.iter().any(|l| *l == want.join(" ")),
        "docs/PROTOCOL.md {heading} must show the example {want:?}"
    );
}

#[test]
fn protocol_doc_shows_the_lod_refs_above_request_bytes() {
    let (req, floors) = refs_above_example();
    let bytes = req
        .encode_frame_as(RequestKind::RecordAndRefsAbove(floors))
        .unwrap();
    assert_doc_shows("### 4.9 `LodRefsAboveRequest` (0x13)", &bytes);
}

#[test]
fn protocol_doc_shows_the_lod_refs_request_bytes() {
    let req = LodRequest {
        id: 7,
        offset: 0x0102_0304_0506_0708,
        size: 4096,
    };
    let bytes = Message::LodRefsRequest(req).encode_frame().unwrap();
    assert_doc_shows("### 4.8 `LodRefsRequest` (0x12)", &bytes);
}

#[test]
fn the_message_type_table_of_the_document_is_the_code() {
    // docs/PROTOCOL.md §3: one row per type, `| 0xNN | `Name` | ...`.
    let doc = include_str!("../../docs/PROTOCOL.md");
    let section = doc
        .split("## 3. Framing")
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .expect("§3 in docs/PROTOCOL.md");
    let mut rows = Vec::new();
    for line in section.lines() {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() > 3 {
            if let Some(hex) = cells[1].strip_prefix("0x") {
                if let Ok(n) = u8::from_str_radix(hex, 16) {
                    rows.push(n);
                }
            }
        }
    }
    let code: Vec<u8> = MessageType::ALL.iter().map(|t| t.as_u8()).collect();
    assert_eq!(rows, code);
}

#[test]
fn the_error_code_table_of_the_document_is_the_code() {
    // docs/PROTOCOL.md §6: one row per code, `| N | `name` | ...`.
    let doc = include_str!("../../docs/PROTOCOL.md");
    let section = doc
        .split("## 6. Error codes")
        .nth(1)
        .and_then(|s| s.split("\n## ").next())
        .expect("§6 in docs/PROTOCOL.md");
    let mut rows = Vec::new();
    for line in section.lines() {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() > 3 {
            if let Ok(n) = cells[1].parse::<u16>() {
                rows.push((n, cells[2].trim_matches('`').to_string()));
            }
        }
    }
    let code: Vec<(u16, String)> = ErrorCode::ALL
        .iter()
        .map(|c| (c.as_u16(), c.as_str().to_string()))
        .collect();
    assert_eq!(rows, code);
}

/// A `Priority` frame of priority −2 then the 0x10 example of §4.3: the
/// whole client side of a prioritized request stream (docs/PROTOCOL.md
/// §4.10).
const PRIORITY_STREAM_BYTES: &str = "05 00 00 00  14  fe ff ff ff  15 00 00 00  10  07 00 00 00 00 00 00 00  08 07 06 05 04 03 02 01  00 10 00 00";

#[test]
fn priority_frame_bytes_and_request_streams() {
    let req = LodRequest {
        id: 7,
        offset: 0x0102_0304_0506_0708,
        size: 4096,
    };
    let p = StreamPriority { priority: -2 };
    assert_wire(Message::Priority(p), "05 00 00 00  14  fe ff ff ff");
    assert_eq!(p.encode_frame().unwrap().len(), PRIORITY_FRAME_LEN);
    assert_eq!(MessageType::from_u8(0x14), Some(MessageType::Priority));
    assert_eq!(MessageType::Priority.as_str(), "priority");
    let bytes = req.encode_stream(RequestKind::Record, Some(p)).unwrap();
    assert_eq!(bytes, hex(PRIORITY_STREAM_BYTES));
    assert_eq!(MAX_REQUEST_STREAM_LEN, 50);
    // Every kind, with and without the frame.
    let (_, floors) = refs_above_example();
    for kind in [
        RequestKind::Record,
        RequestKind::RecordAndRefs,
        RequestKind::RecordAndRefsAbove(floors),
    ] {
        for priority in [None, Some(p), Some(StreamPriority { priority: i32::MIN })] {
            let bytes = req.encode_stream(kind, priority).unwrap();
            assert!(bytes.len() <= MAX_REQUEST_STREAM_LEN);
            assert_eq!(
                decode_prioritized_request_stream(&bytes),
                Ok(RequestStream {
                    request: req,
                    kind,
                    priority
                })
            );
            // Without a priority: the bytes of `encode_frame_as`, which a
            // server that predates the frame reads.
            if priority.is_none() {
                assert_eq!(bytes, req.encode_frame_as(kind).unwrap());
                assert_eq!(decode_any_request_stream(&bytes), Ok((req, kind)));
            } else {
                // Such a server refuses it (and answers with id 0).
                assert_eq!(
                    decode_any_request_stream(&bytes),
                    Err(ProtocolError::UnexpectedMessage {
                        got: MessageType::Priority,
                        context: "on a request stream (expected lod_request, lod_refs_request or lod_refs_above_request)",
                    })
                );
            }
        }
    }
}

#[test]
fn a_priority_frame_goes_once_and_first() {
    let req = LodRequest {
        id: 7,
        offset: 64,
        size: 100,
    };
    let p = StreamPriority { priority: 5 }.encode_frame().unwrap();
    let r = req.encode_frame_as(RequestKind::Record).unwrap();
    // Alone: the stream ends before the request.
    assert_eq!(
        decode_prioritized_request_stream(&p),
        Err(ProtocolError::UnexpectedEnd {
            during: "before the request frame"
        })
    );
    // Twice.
    let twice = [p.clone(), p.clone(), r.clone()].concat();
    assert!(matches!(
        decode_prioritized_request_stream(&twice),
        Err(ProtocolError::UnexpectedMessage {
            got: MessageType::Priority,
            ..
        })
    ));
    // After the request.
    let after = [r.clone(), p.clone()].concat();
    assert_eq!(
        decode_prioritized_request_stream(&after),
        Err(ProtocolError::TrailingData {
            extra: PRIORITY_FRAME_LEN as u64,
            after: "request frame"
        })
    );
    // Cut anywhere: an error, never a request.
    let whole = [p, r].concat();
    for cut in 0..whole.len() {
        assert!(decode_prioritized_request_stream(&whole[..cut]).is_err());
    }
    // A priority frame with a body of the wrong length is malformed.
    let long = hex("06 00 00 00  14  01 00 00 00 00");
    assert!(decode_prioritized_request_stream(&[long, whole.clone()].concat()).is_err());
}

#[test]
fn protocol_doc_shows_the_priority_stream_bytes() {
    assert_doc_shows("### 4.10 `Priority` (0x14)", &hex(PRIORITY_STREAM_BYTES));
}
