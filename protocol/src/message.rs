//! The protocol messages and their field rules.
//!
//! Each message is a plain struct; [`Message`] is the sum of all of them.
//! Their body encoding (see the private `codec` module) follows field declaration order,
//! so **field order is part of the wire format**: do not reorder fields.
//!
//! Every message is checked with [`Message::validate`] both before it is
//! encoded and after it is decoded, so limits hold in both directions.

use std::fmt;

use bincode::{Decode, Encode};

use crate::error::ProtocolError;
use crate::error_code::ErrorCode;
use crate::frame::MessageType;

/// Maximum length in bytes of the `tenant`, `token` and `database` strings.
pub const MAX_NAME_LEN: usize = 256;

/// Maximum length in bytes of a human-readable error message.
/// [`ErrorMsg::new`] truncates longer messages (at a char boundary).
pub const MAX_ERROR_MESSAGE_LEN: usize = 1024;

/// Maximum length of the opaque database header carried by [`Welcome`].
pub const MAX_HEADER_LEN: usize = 8 * 1024 * 1024;

/// Client -> server, first message on the control stream.
///
/// `Debug` prints the token as `<redacted>`, so that neither a log line nor
/// the handshake state machines that hold a `Hello` reveal it.
#[derive(Clone, PartialEq, Eq, Hash, Encode, Decode)]
pub struct Hello {
    /// Protocol version the client speaks ([`crate::PROTOCOL_VERSION`]).
    pub version: u16,
    /// Tenant (account) name.
    pub tenant: String,
    /// Secret token that authenticates the tenant.
    pub token: String,
    /// Name of the database the client wants to stream.
    pub database: String,
}

impl std::fmt::Debug for Hello {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Hello")
            .field("version", &self.version)
            .field("tenant", &self.tenant)
            .field("token", &"<redacted>")
            .field("database", &self.database)
            .finish()
    }
}

impl Hello {
    /// A hello for the current [`crate::PROTOCOL_VERSION`].
    pub fn new(
        tenant: impl Into<String>,
        token: impl Into<String>,
        database: impl Into<String>,
    ) -> Self {
        Hello {
            version: crate::PROTOCOL_VERSION,
            tenant: tenant.into(),
            token: token.into(),
            database: database.into(),
        }
    }

    pub(crate) fn validate(&self) -> Result<(), ProtocolError> {
        check_len("hello.tenant", self.tenant.len(), MAX_NAME_LEN)?;
        check_len("hello.token", self.token.len(), MAX_NAME_LEN)?;
        check_len("hello.database", self.database.len(), MAX_NAME_LEN)
    }
}

/// Per-connection limits announced by the server in [`Welcome`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Encode, Decode)]
pub struct Limits {
    /// Maximum number of requests (request streams) in flight at once.
    pub max_in_flight: u32,
    /// Largest `size` a [`LodRequest`] may ask for.
    pub max_record_size: u32,
    /// The tenant's bandwidth cap in bytes per second, one token bucket shared
    /// by all of the tenant's connections; 0 = unlimited.
    pub max_bytes_per_second: u64,
    /// The server closes the connection after this long without traffic.
    pub idle_timeout_ms: u32,
}

impl Default for Limits {
    /// 64 requests in flight, 16 MiB records, no bandwidth cap, 30 s idle timeout.
    fn default() -> Self {
        Limits {
            max_in_flight: 64,
            max_record_size: 16 * 1024 * 1024,
            max_bytes_per_second: 0,
            idle_timeout_ms: 30_000,
        }
    }
}

/// Server -> client, accepted handshake on the control stream.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Encode, Decode)]
pub struct Welcome {
    /// Protocol version the server speaks (equal to the client's).
    pub version: u16,
    /// Name of the database being served (may be the server's canonical name).
    pub database: String,
    /// Size in bytes of the database file: requests must lie within it.
    pub file_size: u64,
    /// The database header bytes, opaque to this crate (see `planet-core`).
    pub header: Vec<u8>,
    /// Limits that apply to this connection.
    pub limits: Limits,
}

impl Welcome {
    pub(crate) fn validate(&self) -> Result<(), ProtocolError> {
        check_len("welcome.database", self.database.len(), MAX_NAME_LEN)?;
        check_len("welcome.header", self.header.len(), MAX_HEADER_LEN)
    }
}

/// Client -> server, alone on its own bidirectional stream: "send me the
/// `size` bytes at `offset` of the database file".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Encode, Decode)]
pub struct LodRequest {
    /// Client-chosen id, unique among the connection's in-flight requests.
    pub id: u64,
    /// Byte offset of the record in the database file.
    pub offset: u64,
    /// Length of the record in bytes.
    pub size: u32,
}

/// The per-child error floors of a `LodRefsAboveRequest` (0x13,
/// [`RequestKind::RecordAndRefsAbove`]), in metres: the server sends child
/// `k`'s child table only when the largest `error` among that table's
/// references is at least `floors[k]`, and marks it unknown (`0xff`)
/// otherwise. Each floor is finite and at least 0, or +∞ (never sent). On
/// the wire: four `f32` LE, kept here as their bits so that a kind compares
/// and hashes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Encode, Decode)]
pub struct ErrorFloors([u32; 4]);

impl ErrorFloors {
    /// The floors `floors` (metres, child order), if every one is at least
    /// 0 (+∞ allowed; NaN and negative values are refused).
    pub fn new(floors: [f32; 4]) -> Result<ErrorFloors, ProtocolError> {
        let f = ErrorFloors(floors.map(f32::to_bits));
        f.validate()?;
        Ok(f)
    }

    /// The floors in metres, in the record's child order.
    pub fn get(&self) -> [f32; 4] {
        self.0.map(f32::from_bits)
    }

    pub(crate) fn validate(&self) -> Result<(), ProtocolError> {
        match self.get().into_iter().find(|f| f.is_nan() || *f < 0.0) {
            None => Ok(()),
            Some(f) => Err(ProtocolError::InvalidField {
                field: "lod_refs_above_request.floors",
                reason: format!("floor {f} is not a number at least 0"),
            }),
        }
    }
}

/// Client -> server, alone on its own request stream (type 0x13): a
/// [`LodRequest`] that also asks for the child tables of the record's
/// children, but only those whose references' largest error reaches the
/// child's floor ([`ErrorFloors`], docs/PROTOCOL.md §4.9).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Encode, Decode)]
pub struct LodRefsAboveRequest {
    /// Client-chosen id, unique among the connection's in-flight requests.
    pub id: u64,
    /// Byte offset of the record in the database file.
    pub offset: u64,
    /// Length of the record in bytes.
    pub size: u32,
    /// Per-child error floors of the child tables.
    pub floors: ErrorFloors,
}

impl LodRefsAboveRequest {
    /// `req` asking for the child tables above `floors`.
    pub const fn new(req: LodRequest, floors: ErrorFloors) -> LodRefsAboveRequest {
        LodRefsAboveRequest {
            id: req.id,
            offset: req.offset,
            size: req.size,
            floors,
        }
    }

    /// The record request it carries.
    pub fn request(&self) -> LodRequest {
        LodRequest {
            id: self.id,
            offset: self.offset,
            size: self.size,
        }
    }
}

/// Client -> server, the first frame of a request stream when present
/// (type 0x14), before the request frame: the response goes out before
/// those of the connection's lower `priority` (docs/PROTOCOL.md §4.10).
/// Responses of equal priority go in the order their requests arrived, and
/// a request stream without this frame has priority 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Encode, Decode)]
pub struct StreamPriority {
    /// Higher is sent first.
    pub priority: i32,
}

/// What a request stream asks for: the frame type that carries its
/// [`LodRequest`] body.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RequestKind {
    /// `LodRequest` (0x10): the record's bytes.
    Record,
    /// `LodRefsRequest` (0x12): the record's bytes, then the child tables of
    /// its children (at most [`MAX_REFS_TRAILER_LEN`] bytes).
    RecordAndRefs,
    /// `LodRefsAboveRequest` (0x13): as `RecordAndRefs`, but a child's table
    /// comes only when its references' largest error reaches the child's
    /// floor.
    RecordAndRefsAbove(ErrorFloors),
}

impl RequestKind {
    /// The frame type of requests of this kind.
    pub const fn msg_type(self) -> MessageType {
        match self {
            RequestKind::Record => MessageType::LodRequest,
            RequestKind::RecordAndRefs => MessageType::LodRefsRequest,
            RequestKind::RecordAndRefsAbove(_) => MessageType::LodRefsAboveRequest,
        }
    }

    /// The largest number of body bytes after the record in a successful
    /// response: 0, or [`MAX_REFS_TRAILER_LEN`].
    pub const fn max_trailer_len(self) -> u32 {
        match self {
            RequestKind::Record => 0,
            RequestKind::RecordAndRefs | RequestKind::RecordAndRefsAbove(_) => MAX_REFS_TRAILER_LEN,
        }
    }

    /// Whether the response carries child tables after the record.
    pub const fn has_refs(self) -> bool {
        !matches!(self, RequestKind::Record)
    }

    /// The kind a client falls back to when the server does not know this
    /// one (docs/PROTOCOL.md §7): 0x13 → 0x12 → 0x10.
    pub const fn fallback(self) -> Option<RequestKind> {
        match self {
            RequestKind::RecordAndRefsAbove(_) => Some(RequestKind::RecordAndRefs),
            RequestKind::RecordAndRefs => Some(RequestKind::Record),
            RequestKind::Record => None,
        }
    }

    /// `req` as a message of this kind.
    pub const fn message(self, req: LodRequest) -> Message {
        match self {
            RequestKind::Record => Message::LodRequest(req),
            RequestKind::RecordAndRefs => Message::LodRefsRequest(req),
            RequestKind::RecordAndRefsAbove(floors) => {
                Message::LodRefsAboveRequest(LodRefsAboveRequest::new(req, floors))
            }
        }
    }
}

/// Largest trailer after the record in the response to a `LodRefsRequest`:
/// four children, each a count byte and four 24-byte child references
/// (4 × (1 + 4 × 24) = 388; equal to `planet_core::format::MAX_CHILD_TABLES_LEN`,
/// which the server's tests check).
pub const MAX_REFS_TRAILER_LEN: u32 = 4 * (1 + 4 * 24);

impl LodRequest {
    /// Encodes this request as one complete frame of `kind`: a `LodRequest`
    /// frame (as [`LodRequest::encode_frame`]) or a `LodRefsRequest` frame,
    /// both [`crate::LOD_REQUEST_FRAME_LEN`] bytes, or a
    /// `LodRefsAboveRequest` frame
    /// ([`crate::LOD_REFS_ABOVE_REQUEST_FRAME_LEN`] bytes).
    pub fn encode_frame_as(&self, kind: RequestKind) -> Result<Vec<u8>, ProtocolError> {
        kind.message(*self).encode_frame()
    }

    /// The whole client side of a request stream for this request of
    /// `kind`: a `Priority` frame when `priority` is given
    /// ([`crate::PRIORITY_FRAME_LEN`] bytes), then the request frame
    /// ([`LodRequest::encode_frame_as`]).
    pub fn encode_stream(
        &self,
        kind: RequestKind,
        priority: Option<StreamPriority>,
    ) -> Result<Vec<u8>, ProtocolError> {
        let mut out = match priority {
            Some(p) => p.encode_frame()?,
            None => Vec::new(),
        };
        crate::frame::encode_frame_into(&kind.message(*self), &mut out)?;
        Ok(out)
    }
}

/// Outcome of a [`LodRequest`].
#[derive(Debug, Clone, PartialEq, Eq, Hash, Encode, Decode)]
pub enum Status {
    /// Success: the head is followed by exactly `body_len` raw record bytes.
    Ok,
    /// Failure: no body follows (`body_len` is 0).
    Error(ErrorMsg),
}

/// Server -> client, first thing on a request stream's response side.
///
/// On [`Status::Ok`] it is followed by exactly `body_len` raw bytes
/// (`body_len` == the request's `size`; for a `LodRefsRequest`, `size` plus
/// a trailer of at most [`MAX_REFS_TRAILER_LEN`] bytes), then the stream is
/// finished.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Encode, Decode)]
pub struct ResponseHead {
    /// The request's id.
    pub id: u64,
    /// Success, or why the request failed.
    pub status: Status,
    /// Number of raw body bytes after this frame; 0 unless `status` is `Ok`.
    pub body_len: u32,
}

impl ResponseHead {
    /// A success head announcing `body_len` body bytes.
    pub fn ok(id: u64, body_len: u32) -> Self {
        ResponseHead {
            id,
            status: Status::Ok,
            body_len,
        }
    }

    /// A failure head (no body follows). The message is truncated to
    /// [`MAX_ERROR_MESSAGE_LEN`] if needed.
    pub fn error(id: u64, error: ErrorMsg) -> Self {
        ResponseHead {
            id,
            status: Status::Error(ErrorMsg::new(error.code, error.message)),
            body_len: 0,
        }
    }

    pub(crate) fn validate(&self) -> Result<(), ProtocolError> {
        match &self.status {
            Status::Ok => Ok(()),
            Status::Error(e) => {
                e.validate()?;
                if self.body_len != 0 {
                    return Err(ProtocolError::InvalidField {
                        field: "response_head.body_len",
                        reason: format!("must be 0 on error, got {}", self.body_len),
                    });
                }
                Ok(())
            }
        }
    }
}

/// Client -> server on the control stream: advisory cancellation of request
/// `id`. The primary mechanism is stopping the request stream
/// (`recv.stop(STREAM_CANCELLED)`); this message is optional.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Encode, Decode)]
pub struct Cancel {
    /// Id of the request to cancel.
    pub id: u64,
}

/// An error report: numeric code plus human-readable text.
///
/// Sent on the control stream (handshake rejection, fatal protocol errors)
/// and inside [`Status::Error`] for per-request failures.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Encode, Decode)]
pub struct ErrorMsg {
    /// Machine-readable code.
    pub code: ErrorCode,
    /// Human-readable explanation (at most [`MAX_ERROR_MESSAGE_LEN`] bytes).
    pub message: String,
}

impl ErrorMsg {
    /// Builds an error message, truncating `message` to
    /// [`MAX_ERROR_MESSAGE_LEN`] bytes at a char boundary.
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        let mut message = message.into();
        if message.len() > MAX_ERROR_MESSAGE_LEN {
            let mut cut = MAX_ERROR_MESSAGE_LEN;
            while !message.is_char_boundary(cut) {
                cut -= 1;
            }
            message.truncate(cut);
        }
        ErrorMsg { code, message }
    }

    pub(crate) fn validate(&self) -> Result<(), ProtocolError> {
        check_len("error.message", self.message.len(), MAX_ERROR_MESSAGE_LEN)
    }
}

impl fmt::Display for ErrorMsg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} ({}): {}",
            self.code,
            self.code.as_u16(),
            self.message
        )
    }
}

impl std::error::Error for ErrorMsg {}

impl From<ProtocolError> for ErrorMsg {
    fn from(e: ProtocolError) -> Self {
        e.to_error_msg()
    }
}

/// Either side on the control stream: graceful shutdown notice. The sender
/// will close the connection once in-flight work is done.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Encode, Decode)]
pub struct Goodbye {
    /// Why (usually [`ErrorCode::ShuttingDown`]).
    pub reason: ErrorCode,
}

/// Any protocol message.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum Message {
    /// See [`Hello`].
    Hello(Hello),
    /// See [`Welcome`].
    Welcome(Welcome),
    /// See [`ErrorMsg`].
    Error(ErrorMsg),
    /// See [`Goodbye`].
    Goodbye(Goodbye),
    /// See [`Cancel`].
    Cancel(Cancel),
    /// See [`LodRequest`].
    LodRequest(LodRequest),
    /// See [`ResponseHead`].
    ResponseHead(ResponseHead),
    /// A [`LodRequest`] that also asks for the child tables of the record's
    /// children ([`RequestKind::RecordAndRefs`]); type byte 0x12, the same
    /// body as [`Message::LodRequest`].
    LodRefsRequest(LodRequest),
    /// See [`LodRefsAboveRequest`] ([`RequestKind::RecordAndRefsAbove`]).
    LodRefsAboveRequest(LodRefsAboveRequest),
    /// See [`StreamPriority`].
    Priority(StreamPriority),
}

impl Message {
    /// The frame type byte for this message.
    pub fn msg_type(&self) -> MessageType {
        match self {
            Message::Hello(_) => MessageType::Hello,
            Message::Welcome(_) => MessageType::Welcome,
            Message::Error(_) => MessageType::Error,
            Message::Goodbye(_) => MessageType::Goodbye,
            Message::Cancel(_) => MessageType::Cancel,
            Message::LodRequest(_) => MessageType::LodRequest,
            Message::ResponseHead(_) => MessageType::ResponseHead,
            Message::LodRefsRequest(_) => MessageType::LodRefsRequest,
            Message::LodRefsAboveRequest(_) => MessageType::LodRefsAboveRequest,
            Message::Priority(_) => MessageType::Priority,
        }
    }

    /// Checks field limits and consistency rules.
    pub fn validate(&self) -> Result<(), ProtocolError> {
        match self {
            Message::Hello(m) => m.check(),
            Message::Welcome(m) => m.check(),
            Message::Error(m) => m.check(),
            Message::Goodbye(m) => m.check(),
            Message::Cancel(m) => m.check(),
            Message::LodRequest(m) => m.check(),
            Message::ResponseHead(m) => m.check(),
            Message::LodRefsRequest(m) => m.check(),
            Message::LodRefsAboveRequest(m) => m.check(),
            Message::Priority(m) => m.check(),
        }
    }

    /// Encodes this message as one complete frame.
    pub fn encode_frame(&self) -> Result<Vec<u8>, ProtocolError> {
        let mut out = Vec::new();
        crate::frame::encode_frame_into(self, &mut out)?;
        Ok(out)
    }
}

/// A struct that is the body of one frame type.
pub(crate) trait WireBody: Encode + Decode<()> + Into<Message> {
    /// The frame type byte for this body.
    const TYPE: MessageType;
    /// Field limits and consistency rules.
    fn check(&self) -> Result<(), ProtocolError>;
}

macro_rules! impl_wire_body {
    ($($ty:ident => $variant:ident, $check:expr;)*) => {
        $(
            impl From<$ty> for Message {
                fn from(m: $ty) -> Message {
                    Message::$variant(m)
                }
            }

            impl WireBody for $ty {
                const TYPE: MessageType = MessageType::$variant;
                fn check(&self) -> Result<(), ProtocolError> {
                    let check: fn(&$ty) -> Result<(), ProtocolError> = $check;
                    check(self)
                }
            }

            impl $ty {
                /// Encodes this message as one complete frame.
                pub fn encode_frame(&self) -> Result<Vec<u8>, ProtocolError> {
                    let mut out = Vec::new();
                    crate::frame::encode_body_frame(self, &mut out)?;
                    Ok(out)
                }
            }
        )*
    };
}

impl_wire_body! {
    Hello => Hello, Hello::validate;
    Welcome => Welcome, Welcome::validate;
    ErrorMsg => Error, ErrorMsg::validate;
    Goodbye => Goodbye, |_| Ok(());
    Cancel => Cancel, |_| Ok(());
    LodRequest => LodRequest, |_| Ok(());
    ResponseHead => ResponseHead, ResponseHead::validate;
    LodRefsAboveRequest => LodRefsAboveRequest, |m| m.floors.validate();
    StreamPriority => Priority, |_| Ok(());
}

fn check_len(field: &'static str, len: usize, max: usize) -> Result<(), ProtocolError> {
    if len > max {
        Err(ProtocolError::InvalidField {
            field,
            reason: format!("{len} bytes exceeds the limit of {max}"),
        })
    } else {
        Ok(())
    }
}
