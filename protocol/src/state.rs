//! Small sans-IO state machines for the control stream, and the in-flight
//! request tracker.
//!
//! They consume bytes (or decoded messages) and return what to send and what
//! happened; the caller owns all I/O. Decisions that need configuration
//! (who may read what) are delegated to an [`Authorizer`] supplied by the
//! server.

use std::collections::HashSet;

use crate::error::ProtocolError;
use crate::error_code::ErrorCode;
use crate::frame::{FrameDecoder, MAX_FRAME_LEN};
use crate::message::{ErrorMsg, Hello, Limits, LodRequest, Message, Welcome};
use crate::PROTOCOL_VERSION;

/// How the handshake ended, from the client's point of view.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum HandshakeOutcome {
    /// The server accepted the hello.
    Welcomed(Welcome),
    /// The server refused (or said goodbye before welcoming us). The server
    /// closes the connection after sending this.
    Rejected(ErrorMsg),
}

/// Client side of the handshake on the control stream.
///
/// ```
/// use planet_protocol::{ClientHandshake, Hello};
/// let (mut hs, bytes) = ClientHandshake::new(Hello::new("acme", "secret", "earth")).unwrap();
/// // write `bytes` on the control stream, then feed what the server sends:
/// assert_eq!(hs.receive(&[]).unwrap(), None);
/// # let _ = bytes;
/// ```
#[derive(Debug, Clone)]
pub struct ClientHandshake {
    hello: Hello,
    decoder: FrameDecoder,
    outcome: Option<HandshakeOutcome>,
}

impl ClientHandshake {
    /// Starts a handshake: returns the state machine and the bytes (the
    /// `Hello` frame) to write on the freshly opened control stream.
    pub fn new(hello: Hello) -> Result<(Self, Vec<u8>), ProtocolError> {
        let bytes = hello.encode_frame()?;
        let hs = ClientHandshake {
            hello,
            decoder: FrameDecoder::new(),
            outcome: None,
        };
        Ok((hs, bytes))
    }

    /// The hello that was sent.
    pub fn hello(&self) -> &Hello {
        &self.hello
    }

    /// The outcome, once known.
    pub fn outcome(&self) -> Option<&HandshakeOutcome> {
        self.outcome.as_ref()
    }

    /// Feeds bytes received on the control stream. Returns the outcome as soon
    /// as it is known (exactly once); later bytes are kept for
    /// [`ClientHandshake::into_decoder`].
    ///
    /// Errors: malformed frames, a message other than `Welcome`, `Error` or
    /// `Goodbye` before the outcome, or a `Welcome` with another version.
    pub fn receive(&mut self, bytes: &[u8]) -> Result<Option<HandshakeOutcome>, ProtocolError> {
        self.decoder.push(bytes);
        if self.outcome.is_some() {
            return Ok(None);
        }
        let Some(msg) = self.decoder.next_frame()? else {
            return Ok(None);
        };
        let outcome = match msg {
            Message::Welcome(w) => {
                if w.version != self.hello.version {
                    return Err(ProtocolError::UnsupportedVersion {
                        ours: self.hello.version,
                        theirs: w.version,
                    });
                }
                HandshakeOutcome::Welcomed(w)
            }
            Message::Error(e) => HandshakeOutcome::Rejected(e),
            Message::Goodbye(g) => HandshakeOutcome::Rejected(ErrorMsg::new(
                g.reason,
                "server said goodbye before welcome",
            )),
            other => {
                return Err(ProtocolError::UnexpectedMessage {
                    got: other.msg_type(),
                    context: "during the handshake",
                })
            }
        };
        self.outcome = Some(outcome.clone());
        Ok(Some(outcome))
    }

    /// Call if the control stream ends: an error unless the outcome is known.
    pub fn finish(&self) -> Result<(), ProtocolError> {
        if self.outcome.is_some() {
            return Ok(());
        }
        self.decoder.finish()?;
        Err(ProtocolError::UnexpectedEnd {
            during: "before Welcome",
        })
    }

    /// The control-stream decoder, holding any bytes received after the
    /// handshake message (e.g. an early `Goodbye`): keep using it for the
    /// rest of the connection.
    pub fn into_decoder(self) -> FrameDecoder {
        self.decoder
    }
}

/// The server's policy hook: decides whether a [`Hello`] is accepted.
///
/// Implemented by the server (config, token checks, database lookup); this
/// crate only calls it. The version has already been checked when it is
/// called. `Err` should carry `Unauthorized`, `UnknownDatabase`,
/// `Forbidden`, `ServerBusy`, ... Blanket-implemented for closures.
pub trait Authorizer {
    /// Accepts the hello with the returned [`Welcome`] (its `version` is
    /// overwritten with [`PROTOCOL_VERSION`]), or rejects it.
    fn authorize(&self, hello: &Hello) -> Result<Welcome, ErrorMsg>;
}

impl<F> Authorizer for F
where
    F: Fn(&Hello) -> Result<Welcome, ErrorMsg>,
{
    fn authorize(&self, hello: &Hello) -> Result<Welcome, ErrorMsg> {
        self(hello)
    }
}

/// Server-side state of a connection's control stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SessionState {
    /// Waiting for the client's `Hello`.
    AwaitingHello,
    /// Handshake accepted.
    Established {
        /// The authenticated tenant.
        tenant: String,
        /// The database name requested in the hello.
        database: String,
        /// Size of the database file (from the `Welcome`).
        file_size: u64,
        /// Limits announced in the `Welcome`.
        limits: Limits,
    },
    /// A fatal error occurred, or the client said goodbye / ended the
    /// control stream. Further input is ignored.
    Closed,
}

/// Something the server must act on, produced by [`ServerSession`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ServerEvent {
    /// The hello was accepted: write `reply` (the `Welcome` frame) on the
    /// control stream. Request streams may now be served.
    Welcomed {
        /// The welcome that was sent.
        welcome: Welcome,
        /// Encoded `Welcome` frame to write.
        reply: Vec<u8>,
    },
    /// Connection-fatal: write `reply` (the `ErrorMsg` frame), finish the
    /// control stream, then close the connection with
    /// `error.code.to_quic()`. Covers rejected hellos and protocol violations.
    Fatal {
        /// The error reported to the client.
        error: ErrorMsg,
        /// Encoded `ErrorMsg` frame to write.
        reply: Vec<u8>,
    },
    /// The client asked to cancel request `id` (advisory).
    Cancel {
        /// The request id.
        id: u64,
    },
    /// The client is leaving: finish in-flight responses, then close.
    Goodbye {
        /// The client's reason.
        reason: ErrorCode,
    },
    /// The client reported an error on the control stream.
    PeerError(ErrorMsg),
}

/// Server side of a connection's control stream.
///
/// ```
/// use planet_protocol::*;
/// let auth = |h: &Hello| -> Result<Welcome, ErrorMsg> {
///     Ok(Welcome { version: 0, database: h.database.clone(), file_size: 1000,
///                  header: vec![], limits: Limits::default() })
/// };
/// let mut session = ServerSession::new();
/// let hello = Hello::new("acme", "secret", "earth").encode_frame().unwrap();
/// let events = session.receive(&hello, &auth);
/// assert!(matches!(events[0], ServerEvent::Welcomed { .. }));
/// assert!(session.is_established());
/// ```
#[derive(Debug, Clone)]
pub struct ServerSession {
    state: SessionState,
    decoder: FrameDecoder,
}

impl Default for ServerSession {
    fn default() -> Self {
        ServerSession::new()
    }
}

impl ServerSession {
    /// A session awaiting the client's hello.
    pub fn new() -> Self {
        ServerSession {
            state: SessionState::AwaitingHello,
            decoder: FrameDecoder::with_max_frame_len(MAX_FRAME_LEN),
        }
    }

    /// Current state.
    pub fn state(&self) -> &SessionState {
        &self.state
    }

    /// True after an accepted hello and before closing.
    pub fn is_established(&self) -> bool {
        matches!(self.state, SessionState::Established { .. })
    }

    /// True once the session is closed (fatal error, goodbye, end of stream).
    pub fn is_closed(&self) -> bool {
        self.state == SessionState::Closed
    }

    /// The authenticated tenant, once established.
    pub fn tenant(&self) -> Option<&str> {
        match &self.state {
            SessionState::Established { tenant, .. } => Some(tenant),
            _ => None,
        }
    }

    /// The database, once established.
    pub fn database(&self) -> Option<&str> {
        match &self.state {
            SessionState::Established { database, .. } => Some(database),
            _ => None,
        }
    }

    /// Feeds bytes received on the control stream and returns the resulting
    /// events in order. Decoding errors become a [`ServerEvent::Fatal`].
    pub fn receive<A: Authorizer + ?Sized>(
        &mut self,
        bytes: &[u8],
        authorizer: &A,
    ) -> Vec<ServerEvent> {
        let mut events = Vec::new();
        if self.is_closed() {
            return events;
        }
        self.decoder.push(bytes);
        while !self.is_closed() {
            match self.decoder.next_frame() {
                Ok(Some(msg)) => events.extend(self.handle(msg, authorizer)),
                Ok(None) => break,
                Err(e) => events.push(self.fatal(e.to_error_msg())),
            }
        }
        events
    }

    /// Call when the client finishes its side of the control stream.
    /// Returns a [`ServerEvent::Fatal`] if a frame was cut short or no hello
    /// was received; the session is closed afterwards either way.
    pub fn finish(&mut self) -> Option<ServerEvent> {
        match &self.state {
            SessionState::Closed => None,
            SessionState::AwaitingHello => {
                let error = match self.decoder.finish() {
                    Err(e) => e.to_error_msg(),
                    Ok(()) => ErrorMsg::new(
                        ErrorCode::HelloRequired,
                        "control stream ended before hello",
                    ),
                };
                Some(self.fatal(error))
            }
            SessionState::Established { .. } => match self.decoder.finish() {
                Err(e) => Some(self.fatal(e.to_error_msg())),
                Ok(()) => {
                    self.state = SessionState::Closed;
                    None
                }
            },
        }
    }

    /// Handles one decoded control-stream message.
    pub fn handle<A: Authorizer + ?Sized>(
        &mut self,
        msg: Message,
        authorizer: &A,
    ) -> Option<ServerEvent> {
        match (&self.state, msg) {
            (SessionState::Closed, _) => None,
            (SessionState::AwaitingHello, Message::Hello(hello)) => {
                Some(self.on_hello(&hello, authorizer))
            }
            (SessionState::AwaitingHello, other) => Some(self.fatal(ErrorMsg::new(
                ErrorCode::HelloRequired,
                format!("{} received before hello", other.msg_type()),
            ))),
            (SessionState::Established { .. }, Message::Hello(_)) => Some(self.fatal(
                ErrorMsg::new(ErrorCode::DuplicateHello, "hello already received"),
            )),
            (SessionState::Established { .. }, Message::Cancel(c)) => {
                Some(ServerEvent::Cancel { id: c.id })
            }
            (SessionState::Established { .. }, Message::Goodbye(g)) => {
                self.state = SessionState::Closed;
                Some(ServerEvent::Goodbye { reason: g.reason })
            }
            (SessionState::Established { .. }, Message::Error(e)) => {
                Some(ServerEvent::PeerError(e))
            }
            (SessionState::Established { .. }, other) => {
                let err = ProtocolError::UnexpectedMessage {
                    got: other.msg_type(),
                    context: "from a client on the control stream",
                };
                Some(self.fatal(err.to_error_msg()))
            }
        }
    }

    fn on_hello<A: Authorizer + ?Sized>(&mut self, hello: &Hello, authorizer: &A) -> ServerEvent {
        if hello.version != PROTOCOL_VERSION {
            let err = ProtocolError::UnsupportedVersion {
                ours: PROTOCOL_VERSION,
                theirs: hello.version,
            };
            return self.fatal(err.to_error_msg());
        }
        let mut welcome = match authorizer.authorize(hello) {
            Ok(w) => w,
            Err(e) => return self.fatal(e),
        };
        welcome.version = PROTOCOL_VERSION;
        let reply = match welcome.encode_frame() {
            Ok(bytes) => bytes,
            Err(e) => {
                return self.fatal(ErrorMsg::new(
                    ErrorCode::Internal,
                    format!("cannot encode welcome: {e}"),
                ))
            }
        };
        self.state = SessionState::Established {
            tenant: hello.tenant.clone(),
            database: hello.database.clone(),
            file_size: welcome.file_size,
            limits: welcome.limits,
        };
        ServerEvent::Welcomed { welcome, reply }
    }

    fn fatal(&mut self, error: ErrorMsg) -> ServerEvent {
        self.state = SessionState::Closed;
        // Re-normalise (truncate) messages built without `ErrorMsg::new`, so
        // that the frame always encodes.
        let error = ErrorMsg::new(error.code, error.message);
        let reply = error.encode_frame().unwrap_or_default();
        ServerEvent::Fatal { error, reply }
    }

    /// Protocol-level checks of a request received on a request stream:
    /// `HelloRequired` before the handshake, `WrongSize` for `size == 0`,
    /// `RecordTooLarge` over `max_record_size`, `OutOfRange` past the end of
    /// the file. Whether `offset` is a record start (`NotARecord`) and `size`
    /// its length (`WrongSize`) is for the server to check against its index.
    pub fn check_request(&self, req: &LodRequest) -> Result<(), ErrorMsg> {
        let SessionState::Established {
            file_size, limits, ..
        } = &self.state
        else {
            return Err(ErrorMsg::new(
                ErrorCode::HelloRequired,
                "request before the handshake completed",
            ));
        };
        if req.size == 0 {
            return Err(ErrorMsg::new(ErrorCode::WrongSize, "size is 0"));
        }
        if req.size > limits.max_record_size {
            return Err(ErrorMsg::new(
                ErrorCode::RecordTooLarge,
                format!(
                    "size {} exceeds max_record_size {}",
                    req.size, limits.max_record_size
                ),
            ));
        }
        match req.offset.checked_add(u64::from(req.size)) {
            Some(end) if end <= *file_size => Ok(()),
            _ => Err(ErrorMsg::new(
                ErrorCode::OutOfRange,
                format!(
                    "offset {} + size {} is past the end of the file ({} bytes)",
                    req.offset, req.size, file_size
                ),
            )),
        }
    }
}

/// Why [`InFlight::begin`] refused a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum InFlightError {
    /// Already `max` requests in flight.
    #[error("too many requests in flight (max {max})")]
    TooMany {
        /// The limit.
        max: u32,
    },
    /// The id is already in flight.
    #[error("request id {0} is already in flight")]
    Duplicate(u64),
}

impl InFlightError {
    /// The wire code: `TooManyInFlight` or `DuplicateRequest`.
    pub fn code(&self) -> ErrorCode {
        match self {
            InFlightError::TooMany { .. } => ErrorCode::TooManyInFlight,
            InFlightError::Duplicate(_) => ErrorCode::DuplicateRequest,
        }
    }

    /// An [`ErrorMsg`] for the peer.
    pub fn to_error_msg(&self) -> ErrorMsg {
        ErrorMsg::new(self.code(), self.to_string())
    }
}

/// The set of request ids in flight on one connection, bounded by
/// `max_in_flight`. Used by the server (to enforce the limit) and the client
/// (to stay under it and allocate ids).
#[derive(Debug, Clone)]
pub struct InFlight {
    max: u32,
    ids: HashSet<u64>,
    next_id: u64,
}

impl InFlight {
    /// An empty tracker allowing `max` concurrent requests.
    pub fn new(max: u32) -> Self {
        InFlight {
            max,
            ids: HashSet::new(),
            next_id: 0,
        }
    }

    /// The limit.
    pub fn max(&self) -> u32 {
        self.max
    }

    /// Changes the limit (requests already in flight are kept).
    pub fn set_max(&mut self, max: u32) {
        self.max = max;
    }

    /// Number of requests in flight.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True if nothing is in flight.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Free slots under the limit.
    pub fn available(&self) -> usize {
        (self.max as usize).saturating_sub(self.ids.len())
    }

    /// True if `id` is in flight.
    pub fn contains(&self, id: u64) -> bool {
        self.ids.contains(&id)
    }

    /// Registers `id` as in flight.
    pub fn begin(&mut self, id: u64) -> Result<(), InFlightError> {
        if self.ids.contains(&id) {
            return Err(InFlightError::Duplicate(id));
        }
        if self.ids.len() >= self.max as usize {
            return Err(InFlightError::TooMany { max: self.max });
        }
        self.ids.insert(id);
        Ok(())
    }

    /// Client helper: allocates a fresh id (monotonic, skipping ids in
    /// flight) and registers it.
    pub fn begin_next(&mut self) -> Result<u64, InFlightError> {
        if self.ids.len() >= self.max as usize {
            return Err(InFlightError::TooMany { max: self.max });
        }
        while self.ids.contains(&self.next_id) {
            self.next_id = self.next_id.wrapping_add(1);
        }
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1);
        self.begin(id).map(|()| id)
    }

    /// Marks `id` as done (answered, failed or cancelled). Returns false if it
    /// was not in flight.
    pub fn end(&mut self, id: u64) -> bool {
        self.ids.remove(&id)
    }
}
