//! Property tests: arbitrary input never panics the decoders, and
//! encode -> decode is the identity for arbitrary valid messages, however the
//! bytes are fragmented.

use planet_protocol::*;
use proptest::collection::vec;
use proptest::prelude::*;

fn name() -> impl Strategy<Value = String> {
    // Up to 64 chars of up to 4 bytes each stays within MAX_NAME_LEN.
    ".{0,64}"
}

fn error_code() -> impl Strategy<Value = ErrorCode> {
    proptest::sample::select(ErrorCode::ALL.to_vec())
}

fn error_msg() -> impl Strategy<Value = ErrorMsg> {
    (error_code(), ".{0,100}").prop_map(|(code, m)| ErrorMsg::new(code, m))
}

fn limits() -> impl Strategy<Value = Limits> {
    (any::<u32>(), any::<u32>(), any::<u64>(), any::<u32>()).prop_map(|(a, b, c, d)| Limits {
        max_in_flight: a,
        max_record_size: b,
        max_bytes_per_second: c,
        idle_timeout_ms: d,
    })
}

/// A valid error floor: 0, +∞, or any finite `f32` at least 0.
fn floor() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(0.0f32),
        Just(f32::INFINITY),
        (0.0f32..f32::MAX),
        any::<f32>().prop_filter_map("finite, at least 0", |f| {
            (f.is_finite() && f >= 0.0).then_some(f)
        }),
    ]
}

fn message() -> impl Strategy<Value = Message> {
    prop_oneof![
        (any::<u16>(), name(), name(), name()).prop_map(|(version, tenant, token, database)| {
            Message::Hello(Hello {
                version,
                tenant,
                token,
                database,
            })
        }),
        (
            any::<u16>(),
            name(),
            any::<u64>(),
            vec(any::<u8>(), 0..300),
            limits()
        )
            .prop_map(|(version, database, file_size, header, limits)| {
                Message::Welcome(Welcome {
                    version,
                    database,
                    file_size,
                    header,
                    limits,
                })
            }),
        error_msg().prop_map(Message::Error),
        error_code().prop_map(|reason| Message::Goodbye(Goodbye { reason })),
        any::<u64>().prop_map(|id| Message::Cancel(Cancel { id })),
        (any::<u64>(), any::<u64>(), any::<u32>())
            .prop_map(|(id, offset, size)| Message::LodRequest(LodRequest { id, offset, size })),
        (any::<u64>(), any::<u64>(), any::<u32>()).prop_map(|(id, offset, size)| {
            Message::LodRefsRequest(LodRequest { id, offset, size })
        }),
        (
            any::<u64>(),
            any::<u64>(),
            any::<u32>(),
            [floor(), floor(), floor(), floor()]
        )
            .prop_map(|(id, offset, size, f)| {
                let floors = ErrorFloors::new(f).expect("floors at least 0");
                Message::LodRefsAboveRequest(LodRefsAboveRequest::new(
                    LodRequest { id, offset, size },
                    floors,
                ))
            }),
        (any::<u64>(), any::<u32>())
            .prop_map(|(id, len)| Message::ResponseHead(ResponseHead::ok(id, len))),
        (any::<u64>(), error_msg())
            .prop_map(|(id, e)| Message::ResponseHead(ResponseHead::error(id, e))),
        any::<i32>().prop_map(|priority| Message::Priority(StreamPriority { priority })),
    ]
}

/// Feeds `bytes` in chunks of the given sizes (cycled), collecting messages
/// until the first error.
fn decode_chunked(bytes: &[u8], sizes: &[usize]) -> (Vec<Message>, Option<ProtocolError>) {
    let mut dec = FrameDecoder::new();
    let mut out = Vec::new();
    let mut pos = 0;
    let mut i = 0;
    while pos < bytes.len() {
        let n = sizes
            .get(i % sizes.len().max(1))
            .copied()
            .unwrap_or(1)
            .max(1);
        let end = (pos + n).min(bytes.len());
        dec.push(&bytes[pos..end]);
        pos = end;
        i += 1;
        loop {
            match dec.next_frame() {
                Ok(Some(m)) => out.push(m),
                Ok(None) => break,
                Err(e) => return (out, Some(e)),
            }
        }
    }
    (out, dec.finish().err())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn encode_decode_identity(msg in message()) {
        let bytes = msg.encode_frame().unwrap();
        let (decoded, used) = decode_frame(&bytes).unwrap().unwrap();
        prop_assert_eq!(used, bytes.len());
        prop_assert_eq!(&decoded, &msg);
        // Re-encoding gives the same bytes (canonical encoding).
        prop_assert_eq!(decoded.encode_frame().unwrap(), bytes);
    }

    #[test]
    fn fragmented_streams_decode_identically(
        msgs in vec(message(), 0..8),
        sizes in vec(1usize..64, 1..8),
    ) {
        let mut bytes = Vec::new();
        for m in &msgs {
            encode_frame_into(m, &mut bytes).unwrap();
        }
        let (got, err) = decode_chunked(&bytes, &sizes);
        prop_assert_eq!(err, None);
        prop_assert_eq!(got, msgs);
    }

    #[test]
    fn arbitrary_bytes_never_panic(
        bytes in vec(any::<u8>(), 0..512),
        sizes in vec(1usize..32, 1..4),
    ) {
        let (msgs, _err) = decode_chunked(&bytes, &sizes);
        // Whatever decoded is valid and re-encodes.
        for m in msgs {
            prop_assert!(m.validate().is_ok());
            prop_assert!(m.encode_frame().is_ok());
        }
        let _ = decode_frame(&bytes);
        let _ = decode_request_stream(&bytes);
        let _ = decode_any_request_stream(&bytes);
        let _ = decode_prioritized_request_stream(&bytes);
        let req = LodRequest { id: 0, offset: 0, size: 16 };
        let _ = decode_response(&req, &bytes);
        let _ = decode_response_with_refs(&req, &bytes);
    }

    /// Arbitrary bytes behind a plausible frame header (valid type, length
    /// matching the body) exercise the body decoders rather than the header
    /// checks.
    #[test]
    fn arbitrary_bodies_never_panic(
        type_idx in 0usize..MessageType::ALL.len(),
        body in vec(any::<u8>(), 0..128),
    ) {
        let t = MessageType::ALL[type_idx];
        let mut frame = ((body.len() + 1) as u32).to_le_bytes().to_vec();
        frame.push(t.as_u8());
        frame.extend_from_slice(&body);
        match decode_frame(&frame) {
            Ok(Some((m, used))) => {
                prop_assert_eq!(used, frame.len());
                prop_assert_eq!(m.msg_type(), t);
                // Decoding is exact: re-encoding yields the same frame.
                prop_assert_eq!(m.encode_frame().unwrap(), frame);
            }
            Ok(None) => prop_assert!(false, "complete frame reported incomplete"),
            Err(e) => prop_assert_eq!(e.code(), ErrorCode::Malformed),
        }
    }

    /// Flipping bytes of valid frames never panics, and the server session
    /// turns any failure into a Fatal event.
    #[test]
    fn mutated_frames_never_panic(
        msg in message(),
        flips in vec((any::<prop::sample::Index>(), any::<u8>()), 1..4),
    ) {
        let mut bytes = msg.encode_frame().unwrap();
        for (idx, val) in flips {
            let i = idx.index(bytes.len());
            bytes[i] = val;
        }
        let _ = decode_chunked(&bytes, &[3, 7]);
        let auth = |h: &Hello| -> Result<Welcome, ErrorMsg> {
            Ok(Welcome { version: 0, database: h.database.clone(), file_size: 1,
                         header: vec![], limits: Limits::default() })
        };
        let mut s = ServerSession::new();
        let events = s.receive(&bytes, &auth);
        let _ = s.finish();
        // At most one Fatal, always last, and then the session is closed.
        let fatal_at = events.iter().position(|e| matches!(e, ServerEvent::Fatal { .. }));
        if let Some(i) = fatal_at {
            prop_assert_eq!(i, events.len() - 1);
            prop_assert!(s.is_closed());
        }
        let (mut c, _) = ClientHandshake::new(Hello::new("a", "b", "c")).unwrap();
        let _ = c.receive(&bytes);
        let _ = c.finish();
    }

    #[test]
    fn response_stream_any_split(
        id in any::<u64>(),
        body in vec(any::<u8>(), 0..256),
        split in any::<prop::sample::Index>(),
        cut in 0usize..4,
    ) {
        let req = LodRequest { id, offset: 0, size: body.len() as u32 };
        let mut stream = ResponseHead::ok(id, body.len() as u32).encode_frame().unwrap();
        stream.extend_from_slice(&body);
        // Deliver the stream minus its last `cut` bytes, split at `at`.
        let end = stream.len() - cut.min(stream.len());
        let at = split.index(end + 1);
        let mut dec = ResponseDecoder::new(req);
        dec.push(&stream[..at]).unwrap();
        dec.push(&stream[at..end]).unwrap();
        let result = dec.finish();
        if cut == 0 {
            prop_assert_eq!(result, Ok(Response::Record { id, body }));
        } else {
            prop_assert!(result.is_err(), "a truncated stream must not decode");
        }
    }

    #[test]
    fn in_flight_never_exceeds_max(
        max in 0u32..8,
        ops in vec((any::<bool>(), 0u64..12), 0..64),
    ) {
        let mut f = InFlight::new(max);
        let mut model = std::collections::HashSet::new();
        for (begin, id) in ops {
            if begin {
                let r = f.begin(id);
                if model.contains(&id) {
                    prop_assert_eq!(r, Err(InFlightError::Duplicate(id)));
                } else if model.len() >= max as usize {
                    prop_assert_eq!(r, Err(InFlightError::TooMany { max }));
                } else {
                    prop_assert_eq!(r, Ok(()));
                    model.insert(id);
                }
            } else {
                prop_assert_eq!(f.end(id), model.remove(&id));
            }
            prop_assert_eq!(f.len(), model.len());
            prop_assert!(f.len() <= max as usize);
        }
    }
}
