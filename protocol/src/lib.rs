//! `planet-protocol`: the wire protocol between the planet streaming server
//! and its clients, in the sans-IO style of `quinn-proto`.
//!
//! This crate only encodes, decodes and tracks state: it performs no I/O and
//! depends on neither tokio nor quinn. The byte-level specification is
//! `docs/PROTOCOL.md`.
//!
//! - [`frame`]: `u32 LE length | u8 type | body` framing, [`FrameDecoder`].
//! - [`message`]: [`Hello`], [`Welcome`], [`LodRequest`] (sent as a
//!   `LodRequest` or a `LodRefsRequest`, [`RequestKind`]),
//!   [`LodRefsAboveRequest`], [`StreamPriority`], [`ResponseHead`],
//!   [`Cancel`], [`ErrorMsg`], [`Goodbye`] and the [`Message`] sum type.
//! - [`response`]: request streams (an optional priority frame and the
//!   request frame; head + raw record body, plus the child tables for a
//!   `LodRefsRequest`).
//! - [`state`]: [`ClientHandshake`], [`ServerSession`], [`InFlight`].
//! - [`error_code`]: stable [`ErrorCode`]s and QUIC application codes.
//! - `codec` (private): the only user of bincode 2.0.1.

mod codec;
pub mod error;
pub mod error_code;
pub mod frame;
pub mod message;
pub mod response;
pub mod state;

pub use error::ProtocolError;
pub use error_code::{quic, ErrorCode};
pub use frame::{
    decode_frame, encode_frame, encode_frame_into, FrameDecoder, MessageType, FRAME_HEADER_LEN,
    LEN_PREFIX_LEN, LOD_REFS_ABOVE_REQUEST_FRAME_LEN, LOD_REQUEST_FRAME_LEN, MAX_FRAME_LEN,
    MAX_REQUEST_FRAME_LEN, MAX_REQUEST_STREAM_LEN, MAX_WELCOME_FRAME_LEN, PRIORITY_FRAME_LEN,
    RESPONSE_HEAD_OK_FRAME_LEN,
};
pub use message::{
    Cancel, ErrorFloors, ErrorMsg, Goodbye, Hello, Limits, LodRefsAboveRequest, LodRequest,
    Message, RequestKind, ResponseHead, Status, StreamPriority, Welcome, MAX_ERROR_MESSAGE_LEN,
    MAX_HEADER_LEN, MAX_NAME_LEN, MAX_REFS_TRAILER_LEN,
};
pub use response::{
    check_head, check_head_kind, decode_any_request_stream, decode_prioritized_request_stream,
    decode_request_stream, decode_response, decode_response_with_refs, RequestStream, Response,
    ResponseDecoder,
};
pub use state::{
    Authorizer, ClientHandshake, HandshakeOutcome, InFlight, InFlightError, ServerEvent,
    ServerSession, SessionState,
};

/// The protocol version spoken by this crate (sent in `Hello` and `Welcome`).
pub const PROTOCOL_VERSION: u16 = 1;

/// The TLS ALPN protocol identifier for QUIC connections.
pub const ALPN: &[u8] = b"planet/1";
