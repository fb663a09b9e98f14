//! Typed errors for everything that can go wrong while encoding, decoding or
//! driving the protocol state machines. Each error maps to a wire
//! [`ErrorCode`] so it can be reported to the peer.

use crate::error_code::ErrorCode;
use crate::frame::MessageType;
use crate::message::ErrorMsg;

/// A protocol-level failure. Never caused by a panic: every malformed input
/// ends up here.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProtocolError {
    /// A frame's length prefix exceeds the limit (for its type, or for the
    /// decoder when the type is not known yet).
    #[error("frame length {len} exceeds the limit of {max} bytes")]
    FrameTooLarge {
        /// The declared frame length (type byte + body).
        len: u64,
        /// The limit that applies.
        max: u32,
    },
    /// A frame's length prefix is 0: there is not even a type byte.
    #[error("empty frame (length 0)")]
    EmptyFrame,
    /// The frame's type byte is not a known [`MessageType`].
    #[error("unknown message type 0x{0:02x}")]
    UnknownMessageType(u8),
    /// The body of a frame could not be decoded.
    #[error("malformed {msg_type} body: {reason}")]
    Malformed {
        /// The type announced by the frame.
        msg_type: MessageType,
        /// What the decoder complained about.
        reason: String,
    },
    /// A decoded field violates a protocol rule (length limit, consistency).
    #[error("invalid field `{field}`: {reason}")]
    InvalidField {
        /// The offending field, e.g. `"hello.token"`.
        field: &'static str,
        /// Why it is invalid.
        reason: String,
    },
    /// Encoding a body failed.
    #[error("cannot encode {msg_type}: {reason}")]
    Encode {
        /// The message being encoded.
        msg_type: MessageType,
        /// What the encoder complained about.
        reason: String,
    },
    /// The stream ended in the middle of a frame.
    #[error("stream ended inside a frame: {buffered} bytes buffered{}", expected_suffix(*.expected))]
    Truncated {
        /// Bytes of the incomplete frame received so far.
        buffered: usize,
        /// Total frame size (prefix included), when the prefix was complete.
        expected: Option<usize>,
    },
    /// The stream ended before an expected message arrived.
    #[error("stream ended {during}")]
    UnexpectedEnd {
        /// What was awaited, e.g. `"before Welcome"`.
        during: &'static str,
    },
    /// A well-formed message arrived where the protocol does not allow it.
    #[error("unexpected {got} message {context}")]
    UnexpectedMessage {
        /// The message type received.
        got: MessageType,
        /// Where it was received, e.g. `"on a request stream"`.
        context: &'static str,
    },
    /// The peer speaks another protocol version.
    #[error("protocol version mismatch: we speak {ours}, peer speaks {theirs}")]
    UnsupportedVersion {
        /// Our [`crate::PROTOCOL_VERSION`].
        ours: u16,
        /// The peer's version.
        theirs: u16,
    },
    /// A response head carries an id other than its request's.
    #[error("response id {got} does not match request id {expected}")]
    ResponseIdMismatch {
        /// The request id.
        expected: u64,
        /// The id in the response head.
        got: u64,
    },
    /// A successful response head announces a body length other than the
    /// requested size.
    #[error("response body_len {got} does not match requested size {expected}")]
    BodyLengthMismatch {
        /// The requested size.
        expected: u32,
        /// The head's `body_len`.
        got: u32,
    },
    /// A successful response head to a `LodRefsRequest` announces a body
    /// length outside `size ..= size + MAX_REFS_TRAILER_LEN`.
    #[error("response body_len {got} is outside {min}..={max} (the record and its child tables)")]
    BodyLengthOutOfRange {
        /// The requested size (the record alone).
        min: u32,
        /// The requested size plus [`crate::MAX_REFS_TRAILER_LEN`].
        max: u64,
        /// The head's `body_len`.
        got: u32,
    },
    /// The response stream ended before `body_len` body bytes arrived.
    #[error("response body truncated: {received} of {expected} bytes")]
    ShortBody {
        /// The announced body length.
        expected: u32,
        /// Bytes actually received.
        received: u64,
    },
    /// Bytes arrived after the end of a message that must end its stream.
    #[error("{extra} unexpected bytes after the end of the {after}")]
    TrailingData {
        /// How many extra bytes.
        extra: u64,
        /// What they followed, e.g. `"response body"`.
        after: &'static str,
    },
}

fn expected_suffix(expected: Option<usize>) -> String {
    match expected {
        Some(n) => format!(" of {n}"),
        None => String::new(),
    }
}

impl ProtocolError {
    /// The wire error code that describes this error.
    pub fn code(&self) -> ErrorCode {
        match self {
            ProtocolError::FrameTooLarge { .. } => ErrorCode::FrameTooLarge,
            ProtocolError::UnknownMessageType(_) => ErrorCode::UnknownMessage,
            ProtocolError::UnsupportedVersion { .. } => ErrorCode::UnsupportedVersion,
            ProtocolError::EmptyFrame
            | ProtocolError::Malformed { .. }
            | ProtocolError::InvalidField { .. }
            | ProtocolError::Encode { .. }
            | ProtocolError::Truncated { .. }
            | ProtocolError::UnexpectedEnd { .. }
            | ProtocolError::UnexpectedMessage { .. }
            | ProtocolError::ResponseIdMismatch { .. }
            | ProtocolError::BodyLengthMismatch { .. }
            | ProtocolError::BodyLengthOutOfRange { .. }
            | ProtocolError::ShortBody { .. }
            | ProtocolError::TrailingData { .. } => ErrorCode::Malformed,
        }
    }

    /// An [`ErrorMsg`] carrying [`Self::code`] and this error's text, ready to
    /// be sent to the peer.
    pub fn to_error_msg(&self) -> ErrorMsg {
        ErrorMsg::new(self.code(), self.to_string())
    }
}
