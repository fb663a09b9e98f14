//! Stateful: the server's control-stream state machine (`ServerSession`,
//! sans IO) driven by a sequence of operations taken from the input: chunks
//! of bytes in arbitrary fragments, the end of the stream, request checks,
//! with an authorizer that accepts or refuses. After every step it checks
//! that a closed session stays silent, a fatal event closes it and carries a
//! decodable `Error` frame, the Welcome comes at most once and only from an
//! accepting authorizer, requests pass only once established, and cancels,
//! peer errors and goodbyes come only after the Welcome. The corpus is
//! replayed by `server/tests/fuzz_regressions.rs` (`control_session`).
#![no_main]
use libfuzzer_sys::fuzz_target;
use planet_protocol::{
    ErrorCode, ErrorMsg, FrameDecoder, Hello, Limits, LodRequest, Message, ServerEvent,
    ServerSession, Welcome,
};

fuzz_target!(|data: &[u8]| {
    // The first byte picks the authorizer's answer; then operations: a chunk
    // of `op / 4` bytes fed to the session (op % 4 == 0 or 1), the end of the
    // control stream (2), or a request check (3).
    let Some((&mode, mut rest)) = data.split_first() else {
        return;
    };
    let accept = mode & 1 == 0;
    let auth = move |h: &Hello| -> Result<Welcome, ErrorMsg> {
        if accept {
            Ok(Welcome {
                version: 0,
                database: h.database.clone(),
                file_size: 1 << 20,
                header: vec![],
                limits: Limits::default(),
            })
        } else {
            Err(ErrorMsg::new(ErrorCode::Unauthorized, "no"))
        }
    };
    let mut s = ServerSession::new();
    let mut welcomed = 0u32;
    while let Some((&op, r)) = rest.split_first() {
        rest = r;
        let was_closed = s.is_closed();
        let events = match op % 4 {
            0 | 1 => {
                let n = (op as usize / 4).min(rest.len());
                let (chunk, r) = rest.split_at(n);
                rest = r;
                s.receive(chunk, &auth)
            }
            2 => s.finish().into_iter().collect(),
            _ => {
                let req = LodRequest {
                    id: 1,
                    offset: 64,
                    size: 8,
                };
                match s.check_request(&req) {
                    Ok(()) => assert!(s.is_established()),
                    Err(e) => {
                        assert!(!s.is_established());
                        assert_eq!(e.code, ErrorCode::HelloRequired);
                    }
                }
                vec![]
            }
        };
        // A closed session says nothing more.
        assert!(!was_closed || events.is_empty());
        for ev in &events {
            match ev {
                ServerEvent::Welcomed { reply, .. } => {
                    welcomed += 1;
                    assert!(accept, "welcomed by a refusing authorizer");
                    assert!(!reply.is_empty());
                }
                ServerEvent::Fatal { error, reply } => {
                    let mut d = FrameDecoder::new();
                    d.push(reply);
                    match d.next_frame() {
                        Ok(Some(Message::Error(e))) => assert_eq!(e.code, error.code),
                        other => panic!("fatal reply is not an Error frame: {other:?}"),
                    }
                }
                // Only an established session cancels, hears errors or
                // goodbyes.
                ServerEvent::Cancel { .. } | ServerEvent::PeerError(_) | ServerEvent::Goodbye { .. } => {
                    assert_eq!(welcomed, 1)
                }
            }
        }
        if matches!(events.last(), Some(ServerEvent::Fatal { .. })) {
            assert!(s.is_closed(), "a fatal event leaves the session open");
        }
        assert!(welcomed <= 1, "welcomed twice");
        assert!(!s.is_established() || welcomed == 1);
    }
});
