//! Control-stream state machines and the in-flight tracker.

use planet_protocol::*;

/// Accepts tenant "acme" with token "good" on database "earth".
struct TestAuth;

impl Authorizer for TestAuth {
    fn authorize(&self, hello: &Hello) -> Result<Welcome, ErrorMsg> {
        if hello.token != "good" {
            return Err(ErrorMsg::new(ErrorCode::Unauthorized, "bad token"));
        }
        if hello.database != "earth" {
            return Err(ErrorMsg::new(
                ErrorCode::UnknownDatabase,
                "no such database",
            ));
        }
        if hello.tenant != "acme" {
            return Err(ErrorMsg::new(ErrorCode::Forbidden, "not for you"));
        }
        Ok(Welcome {
            version: 0, // overwritten by the session
            database: "earth".into(),
            file_size: 10_000,
            header: b"HDR".to_vec(),
            limits: Limits {
                max_in_flight: 2,
                max_record_size: 1000,
                max_bytes_per_second: 0,
                idle_timeout_ms: 5000,
            },
        })
    }
}

fn hello_frame(tenant: &str, token: &str, db: &str) -> Vec<u8> {
    Hello::new(tenant, token, db).encode_frame().unwrap()
}

fn established() -> ServerSession {
    let mut s = ServerSession::new();
    let ev = s.receive(&hello_frame("acme", "good", "earth"), &TestAuth);
    assert!(matches!(ev.as_slice(), [ServerEvent::Welcomed { .. }]));
    s
}

fn fatal_code(events: &[ServerEvent]) -> ErrorCode {
    match events {
        [ServerEvent::Fatal { error, reply }] => {
            // The reply is the encoded error, ready to send.
            let (msg, _) = decode_frame(reply).unwrap().unwrap();
            assert_eq!(msg, Message::Error(error.clone()));
            error.code
        }
        other => panic!("expected one Fatal event, got {other:?}"),
    }
}

#[test]
fn full_handshake_client_and_server() {
    let (mut client, hello_bytes) =
        ClientHandshake::new(Hello::new("acme", "good", "earth")).unwrap();
    let mut server = ServerSession::new();
    assert_eq!(server.state(), &SessionState::AwaitingHello);

    let events = server.receive(&hello_bytes, &TestAuth);
    let [ServerEvent::Welcomed { welcome, reply }] = events.as_slice() else {
        panic!("{events:?}");
    };
    assert_eq!(welcome.version, PROTOCOL_VERSION);
    assert_eq!(
        server.state(),
        &SessionState::Established {
            tenant: "acme".into(),
            database: "earth".into(),
            file_size: 10_000,
            limits: welcome.limits,
        }
    );
    assert_eq!(server.tenant(), Some("acme"));
    assert_eq!(server.database(), Some("earth"));

    // Deliver the reply in two pieces, plus a Goodbye right behind it.
    let mut wire = reply.clone();
    Goodbye {
        reason: ErrorCode::ShuttingDown,
    }
    .encode_frame()
    .map(|b| wire.extend(b))
    .unwrap();
    assert_eq!(client.receive(&wire[..7]).unwrap(), None);
    assert_eq!(client.outcome(), None);
    let outcome = client.receive(&wire[7..]).unwrap();
    assert_eq!(outcome, Some(HandshakeOutcome::Welcomed(welcome.clone())));
    assert_eq!(client.receive(&[]).unwrap(), None, "outcome reported once");
    client.finish().unwrap();
    // The rest of the control stream continues in the decoder.
    let mut dec = client.into_decoder();
    assert_eq!(
        dec.next_frame().unwrap(),
        Some(Message::Goodbye(Goodbye {
            reason: ErrorCode::ShuttingDown
        }))
    );
}

#[test]
fn server_hello_split_at_every_position() {
    let bytes = hello_frame("acme", "good", "earth");
    for split in 0..=bytes.len() {
        let mut s = ServerSession::new();
        let mut events = s.receive(&bytes[..split], &TestAuth);
        if split < bytes.len() {
            assert!(events.is_empty());
            assert!(!s.is_established());
        }
        events.extend(s.receive(&bytes[split..], &TestAuth));
        assert!(matches!(events.as_slice(), [ServerEvent::Welcomed { .. }]));
        assert!(s.is_established());
    }
}

#[test]
fn rejected_hellos() {
    let cases = [
        ("acme", "bad", "earth", ErrorCode::Unauthorized),
        ("acme", "good", "mars", ErrorCode::UnknownDatabase),
        ("other", "good", "earth", ErrorCode::Forbidden),
    ];
    for (tenant, token, db, code) in cases {
        let mut s = ServerSession::new();
        let events = s.receive(&hello_frame(tenant, token, db), &TestAuth);
        assert_eq!(fatal_code(&events), code);
        assert!(s.is_closed());
        // Closed sessions ignore further input.
        assert!(s
            .receive(&hello_frame("acme", "good", "earth"), &TestAuth)
            .is_empty());
        assert_eq!(s.finish(), None);

        // The client sees Rejected.
        let (mut c, _) = ClientHandshake::new(Hello::new(tenant, token, db)).unwrap();
        let [ServerEvent::Fatal { reply, error }] = events.as_slice() else {
            unreachable!()
        };
        assert_eq!(
            c.receive(reply).unwrap(),
            Some(HandshakeOutcome::Rejected(error.clone()))
        );
    }
}

#[test]
fn unsupported_version() {
    let mut hello = Hello::new("acme", "good", "earth");
    hello.version = 2;
    let mut s = ServerSession::new();
    let events = s.receive(&hello.encode_frame().unwrap(), &TestAuth);
    assert_eq!(fatal_code(&events), ErrorCode::UnsupportedVersion);

    // A client receiving a Welcome with another version fails.
    let (mut c, _) = ClientHandshake::new(Hello::new("a", "b", "c")).unwrap();
    let w = Welcome {
        version: 9,
        database: "c".into(),
        file_size: 0,
        header: vec![],
        limits: Limits::default(),
    };
    assert_eq!(
        c.receive(&w.encode_frame().unwrap()),
        Err(ProtocolError::UnsupportedVersion { ours: 1, theirs: 9 })
    );
}

#[test]
fn request_before_hello() {
    // On the control stream.
    let mut s = ServerSession::new();
    let req = LodRequest {
        id: 1,
        offset: 0,
        size: 10,
    };
    let events = s.receive(&req.encode_frame().unwrap(), &TestAuth);
    assert_eq!(fatal_code(&events), ErrorCode::HelloRequired);
    assert!(s.is_closed());

    // On a request stream, before the handshake.
    let s = ServerSession::new();
    assert_eq!(
        s.check_request(&req).unwrap_err().code,
        ErrorCode::HelloRequired
    );
    // Same via handle() with a Cancel.
    let mut s = ServerSession::new();
    let ev = s.handle(Message::Cancel(Cancel { id: 1 }), &TestAuth);
    assert!(
        matches!(ev, Some(ServerEvent::Fatal { error, .. }) if error.code == ErrorCode::HelloRequired)
    );
}

#[test]
fn duplicate_hello() {
    let mut s = established();
    let events = s.receive(&hello_frame("acme", "good", "earth"), &TestAuth);
    assert_eq!(fatal_code(&events), ErrorCode::DuplicateHello);
    assert!(s.is_closed());
}

#[test]
fn hello_and_duplicate_in_one_read() {
    let mut bytes = hello_frame("acme", "good", "earth");
    bytes.extend(hello_frame("acme", "good", "earth"));
    let mut s = ServerSession::new();
    let events = s.receive(&bytes, &TestAuth);
    assert_eq!(events.len(), 2);
    assert!(matches!(events[0], ServerEvent::Welcomed { .. }));
    assert_eq!(fatal_code(&events[1..]), ErrorCode::DuplicateHello);
}

#[test]
fn established_control_messages() {
    let mut s = established();
    let mut bytes = Cancel { id: 3 }.encode_frame().unwrap();
    bytes.extend(
        ErrorMsg::new(ErrorCode::Internal, "client bug")
            .encode_frame()
            .unwrap(),
    );
    bytes.extend(
        Goodbye {
            reason: ErrorCode::ShuttingDown,
        }
        .encode_frame()
        .unwrap(),
    );
    bytes.extend(Cancel { id: 4 }.encode_frame().unwrap()); // after goodbye: ignored
    let events = s.receive(&bytes, &TestAuth);
    assert_eq!(
        events,
        vec![
            ServerEvent::Cancel { id: 3 },
            ServerEvent::PeerError(ErrorMsg::new(ErrorCode::Internal, "client bug")),
            ServerEvent::Goodbye {
                reason: ErrorCode::ShuttingDown
            },
        ]
    );
    assert!(s.is_closed());
}

#[test]
fn server_only_messages_from_client_are_fatal() {
    let mut s = established();
    let events = s.receive(&ResponseHead::ok(1, 1).encode_frame().unwrap(), &TestAuth);
    assert_eq!(fatal_code(&events), ErrorCode::Malformed);
}

#[test]
fn garbage_on_control_stream_is_fatal() {
    let mut s = ServerSession::new();
    let events = s.receive(&[0xff, 0xff, 0xff, 0xff, 0x01], &TestAuth);
    assert_eq!(fatal_code(&events), ErrorCode::FrameTooLarge);

    let mut s = established();
    let events = s.receive(&[2, 0, 0, 0, 0x42, 0], &TestAuth);
    assert_eq!(fatal_code(&events), ErrorCode::UnknownMessage);
}

#[test]
fn control_stream_end() {
    // Ended before hello.
    let mut s = ServerSession::new();
    let ev = s.finish();
    assert!(
        matches!(ev, Some(ServerEvent::Fatal { error, .. }) if error.code == ErrorCode::HelloRequired)
    );
    // Ended inside a frame.
    let mut s = established();
    assert!(s.receive(&[5, 0, 0], &TestAuth).is_empty());
    let ev = s.finish();
    assert!(
        matches!(ev, Some(ServerEvent::Fatal { error, .. }) if error.code == ErrorCode::Malformed)
    );
    // Clean end after the handshake.
    let mut s = established();
    assert_eq!(s.finish(), None);
    assert!(s.is_closed());

    // Client side: stream ends before any answer, or mid-frame.
    let (c, _) = ClientHandshake::new(Hello::new("a", "b", "c")).unwrap();
    assert_eq!(
        c.finish(),
        Err(ProtocolError::UnexpectedEnd {
            during: "before Welcome"
        })
    );
    let (mut c, _) = ClientHandshake::new(Hello::new("a", "b", "c")).unwrap();
    c.receive(&[9, 0]).unwrap();
    assert!(matches!(c.finish(), Err(ProtocolError::Truncated { .. })));
}

#[test]
fn client_handshake_edge_cases() {
    // Goodbye before Welcome = rejected with that reason.
    let (mut c, bytes) = ClientHandshake::new(Hello::new("a", "b", "c")).unwrap();
    assert_eq!(
        decode_frame(&bytes).unwrap().unwrap().0,
        Message::Hello(c.hello().clone())
    );
    let out = c
        .receive(
            &Goodbye {
                reason: ErrorCode::ServerBusy,
            }
            .encode_frame()
            .unwrap(),
        )
        .unwrap();
    assert!(matches!(out, Some(HandshakeOutcome::Rejected(e)) if e.code == ErrorCode::ServerBusy));
    // Unexpected message during the handshake.
    let (mut c, _) = ClientHandshake::new(Hello::new("a", "b", "c")).unwrap();
    assert!(matches!(
        c.receive(&Cancel { id: 1 }.encode_frame().unwrap()),
        Err(ProtocolError::UnexpectedMessage {
            got: MessageType::Cancel,
            ..
        })
    ));
    // An invalid hello is refused before anything is sent.
    assert!(ClientHandshake::new(Hello::new("x".repeat(300), "b", "c")).is_err());
}

#[test]
fn closure_authorizer() {
    let auth = |h: &Hello| -> Result<Welcome, ErrorMsg> {
        Err(ErrorMsg::new(
            ErrorCode::ServerBusy,
            format!("busy, {}", h.tenant),
        ))
    };
    let mut s = ServerSession::new();
    let events = s.receive(&hello_frame("t", "k", "d"), &auth);
    assert_eq!(fatal_code(&events), ErrorCode::ServerBusy);
}

#[test]
fn oversized_authorizer_error_is_truncated() {
    let auth = |_: &Hello| -> Result<Welcome, ErrorMsg> {
        Err(ErrorMsg {
            code: ErrorCode::Forbidden,
            message: "x".repeat(MAX_ERROR_MESSAGE_LEN * 2),
        })
    };
    let mut s = ServerSession::new();
    let events = s.receive(&hello_frame("t", "k", "d"), &auth);
    assert_eq!(fatal_code(&events), ErrorCode::Forbidden);
}

#[test]
fn check_request_limits() {
    let s = established(); // file_size 10_000, max_record_size 1000
    let ok = |offset, size| LodRequest {
        id: 1,
        offset,
        size,
    };
    assert_eq!(s.check_request(&ok(0, 1000)), Ok(()));
    assert_eq!(s.check_request(&ok(9_000, 1000)), Ok(()));
    let code = |r| s.check_request(&r).unwrap_err().code;
    assert_eq!(code(ok(9_001, 1000)), ErrorCode::OutOfRange);
    assert_eq!(code(ok(u64::MAX, 1)), ErrorCode::OutOfRange);
    assert_eq!(code(ok(0, 1001)), ErrorCode::RecordTooLarge);
    assert_eq!(code(ok(0, 0)), ErrorCode::WrongSize);
}

#[test]
fn in_flight_tracker() {
    let mut f = InFlight::new(2);
    assert!(f.is_empty());
    assert_eq!(f.available(), 2);
    f.begin(10).unwrap();
    assert_eq!(f.begin(10), Err(InFlightError::Duplicate(10)));
    assert_eq!(
        InFlightError::Duplicate(10).code(),
        ErrorCode::DuplicateRequest
    );
    f.begin(11).unwrap();
    let err = f.begin(12).unwrap_err();
    assert_eq!(err, InFlightError::TooMany { max: 2 });
    assert_eq!(err.to_error_msg().code, ErrorCode::TooManyInFlight);
    assert_eq!(f.len(), 2);
    assert_eq!(f.available(), 0);
    assert!(f.contains(11));
    assert!(f.end(10));
    assert!(!f.end(10), "ending twice reports false");
    f.begin(12).unwrap();
    assert!(!f.contains(10));

    f.set_max(1);
    assert_eq!(f.available(), 0);
    assert!(f.begin(13).is_err());
}

#[test]
fn in_flight_id_allocation() {
    let mut f = InFlight::new(3);
    f.begin(1).unwrap();
    assert_eq!(f.begin_next(), Ok(0));
    assert_eq!(f.begin_next(), Ok(2), "skips ids already in flight");
    assert_eq!(f.begin_next(), Err(InFlightError::TooMany { max: 3 }));
    f.end(0);
    assert_eq!(f.begin_next(), Ok(3));
}
