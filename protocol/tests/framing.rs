//! Framing and request-stream decoding: fragmentation, limits, malformed input.

use planet_protocol::*;

fn sample_messages() -> Vec<Message> {
    vec![
        Hello::new("acme", "s3cr3t", "earth").into(),
        Welcome {
            version: PROTOCOL_VERSION,
            database: "earth".into(),
            file_size: 123_456_789,
            header: (0..=255u8).collect(),
            limits: Limits::default(),
        }
        .into(),
        ErrorMsg::new(ErrorCode::Forbidden, "tenant acme may not read mars").into(),
        Goodbye {
            reason: ErrorCode::ShuttingDown,
        }
        .into(),
        Cancel { id: u64::MAX }.into(),
        LodRequest {
            id: 42,
            offset: 1 << 40,
            size: 65_000,
        }
        .into(),
        ResponseHead::ok(42, 65_000).into(),
        ResponseHead::error(43, ErrorMsg::new(ErrorCode::NotARecord, "misaligned")).into(),
        // Empty strings and header are valid.
        Hello::new("", "", "").into(),
    ]
}

fn stream_of(msgs: &[Message]) -> Vec<u8> {
    let mut out = Vec::new();
    for m in msgs {
        encode_frame_into(m, &mut out).unwrap();
    }
    out
}

fn drain(dec: &mut FrameDecoder, out: &mut Vec<Message>) {
    while let Some(m) = dec.next_frame().unwrap() {
        out.push(m);
    }
}

#[test]
fn every_message_round_trips() {
    for msg in sample_messages() {
        let bytes = msg.encode_frame().unwrap();
        let (decoded, used) = decode_frame(&bytes).unwrap().unwrap();
        assert_eq!(decoded, msg);
        assert_eq!(used, bytes.len());
        // The length prefix counts the type byte and the body.
        let len = u32::from_le_bytes(bytes[..4].try_into().unwrap()) as usize;
        assert_eq!(len, bytes.len() - 4);
        assert_eq!(bytes[4], msg.msg_type().as_u8());
        // Through the incremental decoder too.
        let mut dec = FrameDecoder::new();
        dec.push(&bytes);
        assert_eq!(dec.next_frame().unwrap(), Some(msg));
        assert_eq!(dec.next_frame().unwrap(), None);
        dec.finish().unwrap();
    }
}

#[test]
fn split_at_every_position() {
    let msgs = sample_messages();
    let bytes = stream_of(&msgs);
    for split in 0..=bytes.len() {
        let mut dec = FrameDecoder::new();
        let mut got = Vec::new();
        dec.push(&bytes[..split]);
        drain(&mut dec, &mut got);
        dec.push(&bytes[split..]);
        drain(&mut dec, &mut got);
        dec.finish().unwrap();
        assert_eq!(got, msgs, "split at {split}");
    }
}

#[test]
fn byte_at_a_time_and_three_way_splits() {
    let msgs = sample_messages()[2..].to_vec(); // skip the big Welcome for speed
    let bytes = stream_of(&msgs);

    let mut dec = FrameDecoder::new();
    let mut got = Vec::new();
    for b in &bytes {
        dec.push(std::slice::from_ref(b));
        drain(&mut dec, &mut got);
    }
    dec.finish().unwrap();
    assert_eq!(got, msgs);

    for a in (0..=bytes.len()).step_by(3) {
        for b in (a..=bytes.len()).step_by(5) {
            let mut dec = FrameDecoder::new();
            let mut got = Vec::new();
            for chunk in [&bytes[..a], &bytes[a..b], &bytes[b..]] {
                dec.push(chunk);
                drain(&mut dec, &mut got);
            }
            dec.finish().unwrap();
            assert_eq!(got, msgs, "splits at {a}, {b}");
        }
    }
}

#[test]
fn truncated_stream_is_reported() {
    let bytes = Hello::new("acme", "t", "earth").encode_frame().unwrap();
    for cut in 1..bytes.len() {
        let mut dec = FrameDecoder::new();
        dec.push(&bytes[..cut]);
        assert_eq!(dec.next_frame().unwrap(), None);
        let expected = (cut >= 4).then_some(bytes.len());
        assert_eq!(
            dec.finish(),
            Err(ProtocolError::Truncated {
                buffered: cut,
                expected
            }),
            "cut at {cut}"
        );
        assert_eq!(dec.finish().unwrap_err().code(), ErrorCode::Malformed);
    }
    // An undrained complete frame at end of stream is reported too.
    let mut dec = FrameDecoder::new();
    dec.push(&bytes);
    assert!(matches!(
        dec.finish(),
        Err(ProtocolError::TrailingData { .. })
    ));
}

#[test]
fn oversized_frames_are_rejected_from_the_header() {
    // A control frame one byte over the limit: rejected from 5 bytes alone.
    let mut dec = FrameDecoder::new();
    dec.push(&(MAX_FRAME_LEN + 1).to_le_bytes());
    dec.push(&[MessageType::Hello.as_u8()]);
    let err = dec.next_frame().unwrap_err();
    assert_eq!(
        err,
        ProtocolError::FrameTooLarge {
            len: u64::from(MAX_FRAME_LEN) + 1,
            max: MAX_FRAME_LEN
        }
    );
    assert_eq!(err.code(), ErrorCode::FrameTooLarge);
    // The decoder is poisoned and drops further input.
    dec.push(&[0; 100]);
    assert_eq!(dec.next_frame().unwrap_err(), err);
    assert_eq!(dec.buffered(), 0);

    // A Welcome may be larger than MAX_FRAME_LEN, but not over its own limit.
    let mut dec = FrameDecoder::new();
    let mut head = (MAX_FRAME_LEN + 1).to_le_bytes().to_vec();
    head.push(MessageType::Welcome.as_u8());
    dec.push(&head);
    assert_eq!(
        dec.next_frame().unwrap(),
        None,
        "legal size, waits for body"
    );
    let mut dec = FrameDecoder::new();
    dec.push(&(MAX_WELCOME_FRAME_LEN + 1).to_le_bytes());
    assert!(matches!(
        dec.next_frame(),
        Err(ProtocolError::FrameTooLarge { .. })
    ));

    // A decoder capped at MAX_FRAME_LEN (the server's) rejects big Welcomes
    // from the length prefix alone.
    let mut dec = FrameDecoder::with_max_frame_len(MAX_FRAME_LEN);
    dec.push(&u32::MAX.to_le_bytes());
    assert_eq!(
        dec.next_frame(),
        Err(ProtocolError::FrameTooLarge {
            len: u64::from(u32::MAX),
            max: MAX_FRAME_LEN
        })
    );
}

#[test]
fn oversized_messages_are_not_encoded() {
    let big = Welcome {
        version: 1,
        database: "x".into(),
        file_size: 0,
        header: vec![0; MAX_HEADER_LEN + 1],
        limits: Limits::default(),
    };
    let err = big.encode_frame().unwrap_err();
    assert!(matches!(
        err,
        ProtocolError::InvalidField {
            field: "welcome.header",
            ..
        }
    ));
    // Exactly at the limit is fine and decodes.
    let max = Welcome {
        header: vec![7; MAX_HEADER_LEN],
        ..big
    };
    let bytes = max.encode_frame().unwrap();
    assert!(bytes.len() - 4 <= MAX_WELCOME_FRAME_LEN as usize);
    assert_eq!(
        decode_frame(&bytes).unwrap().unwrap().0,
        Message::Welcome(max)
    );

    let long = "x".repeat(MAX_NAME_LEN + 1);
    for hello in [
        Hello::new(long.clone(), "t", "d"),
        Hello::new("t", long.clone(), "d"),
        Hello::new("t", "t", long.clone()),
    ] {
        assert!(matches!(
            hello.encode_frame(),
            Err(ProtocolError::InvalidField { .. })
        ));
    }
    assert!(Hello::new("x".repeat(MAX_NAME_LEN), "t", "d")
        .encode_frame()
        .is_ok());

    // Encoding into a buffer leaves it untouched on failure.
    let mut out = vec![1, 2, 3];
    assert!(encode_frame_into(&Hello::new(long, "t", "d").into(), &mut out).is_err());
    assert_eq!(out, [1, 2, 3]);
}

#[test]
fn error_messages_are_truncated_at_a_char_boundary() {
    let e = ErrorMsg::new(ErrorCode::Internal, "é".repeat(MAX_ERROR_MESSAGE_LEN));
    assert!(e.message.len() <= MAX_ERROR_MESSAGE_LEN);
    assert_eq!(e.message.len(), MAX_ERROR_MESSAGE_LEN); // 2-byte chars, even limit
    let odd = ErrorMsg::new(
        ErrorCode::Internal,
        format!("a{}", "é".repeat(MAX_ERROR_MESSAGE_LEN)),
    );
    assert_eq!(odd.message.len(), MAX_ERROR_MESSAGE_LEN - 1);
    assert!(e.encode_frame().is_ok());
}

/// Builds a frame with an arbitrary type byte and body.
fn raw_frame(type_byte: u8, body: &[u8]) -> Vec<u8> {
    let mut out = ((body.len() + 1) as u32).to_le_bytes().to_vec();
    out.push(type_byte);
    out.extend_from_slice(body);
    out
}

#[test]
fn unknown_types_are_rejected() {
    for t in [0x00u8, 0x06, 0x0f, 0x15, 0x7f, 0xff] {
        let mut dec = FrameDecoder::new();
        dec.push(&raw_frame(t, &[1, 2, 3]));
        let err = dec.next_frame().unwrap_err();
        assert_eq!(err, ProtocolError::UnknownMessageType(t));
        assert_eq!(err.code(), ErrorCode::UnknownMessage);
    }
    // Rejected from the header, before the (huge) body arrives.
    let mut dec = FrameDecoder::new();
    dec.push(&[0x00, 0x01, 0x00, 0x00, 0x99]);
    assert_eq!(
        dec.next_frame(),
        Err(ProtocolError::UnknownMessageType(0x99))
    );
}

#[test]
fn empty_frame_is_rejected() {
    let mut dec = FrameDecoder::new();
    dec.push(&[0, 0, 0, 0]);
    assert_eq!(dec.next_frame(), Err(ProtocolError::EmptyFrame));
}

#[test]
fn malformed_bodies_are_rejected() {
    let cases: Vec<(&str, Vec<u8>)> = vec![
        // Cancel body one byte short.
        ("short cancel", raw_frame(0x05, &[0; 7])),
        // Cancel with a trailing byte.
        ("trailing byte", raw_frame(0x05, &[0; 9])),
        // Goodbye with an unknown error code.
        ("unknown code", raw_frame(0x04, &[0xff, 0xff])),
        // Goodbye with code 0.
        ("code zero", raw_frame(0x04, &[0, 0])),
        // Error message that is not UTF-8.
        (
            "bad utf8",
            raw_frame(0x03, &[2, 0, 2, 0, 0, 0, 0, 0, 0, 0, 0xc3, 0x28]),
        ),
        // ResponseHead with status variant 2.
        (
            "bad variant",
            raw_frame(0x11, &[0, 0, 0, 0, 0, 0, 0, 0, 2, 0, 0, 0, 0, 0, 0, 0]),
        ),
        // A Hello whose tenant claims 2^40 bytes: must fail without allocating.
        ("huge string claim", {
            let mut body = vec![1, 0];
            body.extend_from_slice(&(1u64 << 40).to_le_bytes());
            raw_frame(0x01, &body)
        }),
        ("max string claim", {
            let mut body = vec![1, 0];
            body.extend_from_slice(&u64::MAX.to_le_bytes());
            raw_frame(0x01, &body)
        }),
    ];
    for (name, frame) in cases {
        let mut dec = FrameDecoder::new();
        dec.push(&frame);
        let err = dec.next_frame().unwrap_err();
        assert!(
            matches!(err, ProtocolError::Malformed { .. }),
            "{name}: {err:?}"
        );
        assert_eq!(err.code(), ErrorCode::Malformed, "{name}");
        assert_eq!(err.to_error_msg().code, ErrorCode::Malformed);
    }
}

#[test]
fn field_limits_are_checked_on_decode() {
    // A Hello with a 257-byte tenant, encoded by hand.
    let mut body = vec![1, 0];
    let tenant = vec![b'a'; MAX_NAME_LEN + 1];
    body.extend_from_slice(&(tenant.len() as u64).to_le_bytes());
    body.extend_from_slice(&tenant);
    for _ in 0..2 {
        body.extend_from_slice(&0u64.to_le_bytes());
    }
    let err = decode_frame(&raw_frame(0x01, &body)).unwrap_err();
    assert!(matches!(
        err,
        ProtocolError::InvalidField {
            field: "hello.tenant",
            ..
        }
    ));

    // An error ResponseHead with a non-zero body_len.
    let mut frame = ResponseHead::error(1, ErrorMsg::new(ErrorCode::Internal, ""))
        .encode_frame()
        .unwrap();
    let n = frame.len();
    frame[n - 4..].copy_from_slice(&5u32.to_le_bytes());
    assert!(matches!(
        decode_frame(&frame),
        Err(ProtocolError::InvalidField {
            field: "response_head.body_len",
            ..
        })
    ));
}

#[test]
fn request_stream() {
    let req = LodRequest {
        id: 9,
        offset: 100,
        size: 20,
    };
    let bytes = req.encode_frame().unwrap();
    assert_eq!(decode_request_stream(&bytes), Ok(req));

    let mut extra = bytes.clone();
    extra.push(0);
    assert_eq!(
        decode_request_stream(&extra),
        Err(ProtocolError::TrailingData {
            extra: 1,
            after: "request frame"
        })
    );
    assert!(matches!(
        decode_request_stream(&bytes[..10]),
        Err(ProtocolError::Truncated { .. })
    ));
    assert_eq!(
        decode_request_stream(&[]),
        Err(ProtocolError::UnexpectedEnd {
            during: "before the request frame"
        })
    );
    let hello = Hello::new("a", "b", "c").encode_frame().unwrap();
    assert!(matches!(
        decode_request_stream(&hello),
        Err(ProtocolError::UnexpectedMessage {
            got: MessageType::Hello,
            ..
        })
    ));
}

#[test]
fn request_stream_of_either_kind() {
    let req = LodRequest {
        id: 9,
        offset: 100,
        size: 20,
    };
    let plain = req.encode_frame().unwrap();
    let refs = Message::LodRefsRequest(req).encode_frame().unwrap();
    assert_eq!(refs.len(), LOD_REQUEST_FRAME_LEN);
    assert_eq!(plain[..4], refs[..4]);
    assert_eq!(plain[5..], refs[5..]);
    assert_eq!(
        decode_any_request_stream(&plain),
        Ok((req, RequestKind::Record))
    );
    assert_eq!(
        decode_any_request_stream(&refs),
        Ok((req, RequestKind::RecordAndRefs))
    );
    // The plain decoder still takes only LodRequest.
    assert_eq!(
        decode_request_stream(&refs),
        Err(ProtocolError::UnexpectedMessage {
            got: MessageType::LodRefsRequest,
            context: "on a request stream (expected lod_request)",
        })
    );
    // The same framing rules for both kinds.
    let mut extra = refs.clone();
    extra.push(0);
    assert_eq!(
        decode_any_request_stream(&extra),
        Err(ProtocolError::TrailingData {
            extra: 1,
            after: "request frame"
        })
    );
    for cut in 0..refs.len() {
        assert!(
            decode_any_request_stream(&refs[..cut]).is_err(),
            "cut {cut}"
        );
    }
    let mut short = refs.clone();
    short[0] = 20;
    short.truncate(4 + 20);
    assert!(matches!(
        decode_any_request_stream(&short),
        Err(ProtocolError::Malformed {
            msg_type: MessageType::LodRefsRequest,
            ..
        })
    ));
    let hello = Hello::new("a", "b", "c").encode_frame().unwrap();
    assert!(matches!(
        decode_any_request_stream(&hello),
        Err(ProtocolError::UnexpectedMessage {
            got: MessageType::Hello,
            ..
        })
    ));
    // A request frame on the control stream is a protocol error there.
    let mut dec = FrameDecoder::new();
    dec.push(&refs);
    assert_eq!(dec.next_frame(), Ok(Some(Message::LodRefsRequest(req))));
}

fn response_stream(head: &ResponseHead, body: &[u8]) -> Vec<u8> {
    let mut out = head.encode_frame().unwrap();
    out.extend_from_slice(body);
    out
}

#[test]
fn response_decoding_split_at_every_position() {
    let req = LodRequest {
        id: 5,
        offset: 0,
        size: 300,
    };
    let body: Vec<u8> = (0..300u32).map(|i| (i * 7) as u8).collect();
    let stream = response_stream(&ResponseHead::ok(5, 300), &body);
    for split in 0..=stream.len() {
        let mut dec = ResponseDecoder::new(req);
        dec.push(&stream[..split]).unwrap();
        assert_eq!(dec.head().is_some(), split >= RESPONSE_HEAD_OK_FRAME_LEN);
        dec.push(&stream[split..]).unwrap();
        assert!(dec.is_complete());
        assert_eq!(
            dec.finish().unwrap(),
            Response::Record {
                id: 5,
                body: body.clone()
            },
            "split at {split}"
        );
    }
}

#[test]
fn short_response_body_is_an_error() {
    let req = LodRequest {
        id: 5,
        offset: 0,
        size: 300,
    };
    let stream = response_stream(&ResponseHead::ok(5, 300), &[1; 300]);
    // Every proper prefix of the stream (a truncated or dropped stream) fails.
    for cut in 0..stream.len() {
        let err = decode_response(&req, &stream[..cut]).unwrap_err();
        if cut >= RESPONSE_HEAD_OK_FRAME_LEN {
            assert_eq!(
                err,
                ProtocolError::ShortBody {
                    expected: 300,
                    received: (cut - RESPONSE_HEAD_OK_FRAME_LEN) as u64
                }
            );
        } else {
            assert!(
                matches!(
                    err,
                    ProtocolError::Truncated { .. } | ProtocolError::UnexpectedEnd { .. }
                ),
                "cut {cut}: {err:?}"
            );
        }
    }
}

#[test]
fn response_mismatches_are_errors() {
    let req = LodRequest {
        id: 5,
        offset: 0,
        size: 3,
    };
    assert_eq!(
        decode_response(&req, &response_stream(&ResponseHead::ok(6, 3), b"abc")),
        Err(ProtocolError::ResponseIdMismatch {
            expected: 5,
            got: 6
        })
    );
    assert_eq!(
        decode_response(&req, &response_stream(&ResponseHead::ok(5, 4), b"abcd")),
        Err(ProtocolError::BodyLengthMismatch {
            expected: 3,
            got: 4
        })
    );
    assert_eq!(
        decode_response(&req, &response_stream(&ResponseHead::ok(5, 3), b"abcd")),
        Err(ProtocolError::TrailingData {
            extra: 1,
            after: "response body"
        })
    );
    // After an error the decoder stays failed.
    let mut dec = ResponseDecoder::new(req);
    assert!(dec
        .push(&response_stream(&ResponseHead::ok(6, 3), b""))
        .is_err());
    assert!(dec.push(b"abc").is_err());
    assert!(dec.finish().is_err());
    // A non-head frame on a response stream.
    assert!(matches!(
        decode_response(&req, &Cancel { id: 5 }.encode_frame().unwrap()),
        Err(ProtocolError::UnexpectedMessage {
            got: MessageType::Cancel,
            ..
        })
    ));
}

#[test]
fn error_response() {
    let req = LodRequest {
        id: 5,
        offset: 0,
        size: 3,
    };
    let e = ErrorMsg::new(ErrorCode::WrongSize, "record at 0 is 4 bytes");
    let stream = response_stream(&ResponseHead::error(5, e.clone()), b"");
    assert_eq!(
        decode_response(&req, &stream),
        Ok(Response::Error { id: 5, error: e })
    );
    // No body may follow an error head.
    let mut extra = stream.clone();
    extra.push(0);
    assert!(matches!(
        decode_response(&req, &extra),
        Err(ProtocolError::TrailingData { .. })
    ));
}

#[test]
fn refs_response_body_lengths() {
    let req = LodRequest {
        id: 5,
        offset: 0,
        size: 300,
    };
    let max = 300 + MAX_REFS_TRAILER_LEN;
    for len in [300, 301, 300 + 4, 300 + 4 + 2 * 96, max] {
        let body: Vec<u8> = (0..len).map(|i| (i * 3) as u8).collect();
        let stream = response_stream(&ResponseHead::ok(5, len), &body);
        assert_eq!(
            decode_response_with_refs(&req, &stream),
            Ok(Response::Record {
                id: 5,
                body: body.clone()
            }),
            "body_len {len}"
        );
        // Split anywhere.
        for split in [0, 10, RESPONSE_HEAD_OK_FRAME_LEN, stream.len() / 2] {
            let mut dec = ResponseDecoder::with_refs(req);
            assert_eq!(dec.kind(), RequestKind::RecordAndRefs);
            dec.push(&stream[..split]).unwrap();
            dec.push(&stream[split..]).unwrap();
            assert!(dec.is_complete());
            assert_eq!(
                dec.finish().unwrap(),
                Response::Record {
                    id: 5,
                    body: body.clone()
                }
            );
        }
        // The plain decoder wants exactly `size`.
        if len != 300 {
            assert_eq!(
                decode_response(&req, &stream),
                Err(ProtocolError::BodyLengthMismatch {
                    expected: 300,
                    got: len
                })
            );
        }
    }
    for len in [0, 299, max + 1, u32::MAX] {
        let head = ResponseHead::ok(5, len);
        assert_eq!(
            decode_response_with_refs(&req, &head.encode_frame().unwrap()),
            Err(ProtocolError::BodyLengthOutOfRange {
                min: 300,
                max: u64::from(max),
                got: len
            }),
            "body_len {len}"
        );
        assert_eq!(
            check_head_kind(&req, RequestKind::RecordAndRefs, &head)
                .unwrap_err()
                .code(),
            ErrorCode::Malformed
        );
    }
    // No overflow next to u32::MAX.
    let big = LodRequest {
        id: 1,
        offset: 0,
        size: u32::MAX - 10,
    };
    assert_eq!(
        check_head_kind(
            &big,
            RequestKind::RecordAndRefs,
            &ResponseHead::ok(1, u32::MAX)
        ),
        Ok(())
    );
    // The other checks are those of the plain decoder: id, short body,
    // trailing bytes, error heads.
    let stream = response_stream(&ResponseHead::ok(6, 300), &[0; 300]);
    assert_eq!(
        decode_response_with_refs(&req, &stream),
        Err(ProtocolError::ResponseIdMismatch {
            expected: 5,
            got: 6
        })
    );
    let stream = response_stream(&ResponseHead::ok(5, 310), &[0; 305]);
    assert_eq!(
        decode_response_with_refs(&req, &stream),
        Err(ProtocolError::ShortBody {
            expected: 310,
            received: 305
        })
    );
    let stream = response_stream(&ResponseHead::ok(5, 310), &[0; 311]);
    assert_eq!(
        decode_response_with_refs(&req, &stream),
        Err(ProtocolError::TrailingData {
            extra: 1,
            after: "response body"
        })
    );
    let e = ErrorMsg::new(ErrorCode::OutOfRange, "no");
    let stream = response_stream(&ResponseHead::error(5, e.clone()), b"");
    assert_eq!(
        decode_response_with_refs(&req, &stream),
        Ok(Response::Error { id: 5, error: e })
    );
}
