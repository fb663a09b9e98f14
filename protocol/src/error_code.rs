//! Stable numeric error codes shared by every message that reports a failure,
//! plus the QUIC application error codes used on streams and connections.
//!
//! The numeric values are part of the wire protocol: never renumber a variant,
//! only append new ones (and bump [`crate::PROTOCOL_VERSION`] when you do, since
//! a peer rejects codes it does not know as malformed).

use std::fmt;

use bincode::de::Decoder;
use bincode::enc::Encoder;
use bincode::error::{DecodeError, EncodeError};
use bincode::{Decode, Encode};

/// Why a request, a handshake or a connection failed.
///
/// Encoded on the wire as a `u16` (little-endian). [`ErrorCode::as_str`] gives a
/// stable snake_case name suitable as a metric label.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u16)]
pub enum ErrorCode {
    /// The peer speaks a protocol version we do not support.
    UnsupportedVersion = 1,
    /// Authentication failed (bad or unknown token).
    Unauthorized = 2,
    /// The requested database does not exist on this server.
    UnknownDatabase = 3,
    /// The tenant is authenticated but may not read that database.
    Forbidden = 4,
    /// A request (or any message other than `Hello`) arrived before the handshake.
    HelloRequired = 5,
    /// A frame body could not be decoded or a field is invalid.
    Malformed = 6,
    /// A frame is longer than the limit for its message type.
    FrameTooLarge = 7,
    /// A frame carries a message type this version does not know.
    UnknownMessage = 8,
    /// `offset`/`size` lie outside the database file.
    OutOfRange = 9,
    /// `offset` is not the start of a record.
    NotARecord = 10,
    /// `size` is not the length of the record at `offset`.
    WrongSize = 11,
    /// `size` exceeds the negotiated `max_record_size`.
    RecordTooLarge = 12,
    /// More requests in flight than the negotiated `max_in_flight`.
    TooManyInFlight = 13,
    /// The tenant exceeded its bandwidth or request rate.
    RateLimited = 14,
    /// The server refuses new connections (connection limit reached).
    ServerBusy = 15,
    /// The record failed its checksum on the server.
    CorruptRecord = 16,
    /// The request was cancelled.
    Cancelled = 17,
    /// The server is shutting down.
    ShuttingDown = 18,
    /// Unexpected server-side failure (I/O error, bug).
    Internal = 19,
    /// A second `Hello` on an established session.
    DuplicateHello = 20,
    /// A request id that is already in flight on this connection.
    DuplicateRequest = 21,
    /// The peer did not finish sending or receiving in time: a request
    /// stream not completed within the server's request-read deadline, a
    /// response not taken within its write deadline, or a connection not
    /// authenticated within the handshake deadline.
    /// Sent only as a QUIC application code (`stop`/`reset`), never in a
    /// message body; see docs/PROTOCOL.md §6.
    Timeout = 22,
    /// The server could not read the record from its storage (a database
    /// file truncated or failing under it). Per request; the session stays
    /// usable and other records may still be served. Like `Timeout`, sent
    /// only as a QUIC application code (`reset` of the request stream),
    /// never in a message body; see docs/PROTOCOL.md §6.
    Storage = 23,
}

impl ErrorCode {
    /// Every code, in numeric order (handy to pre-register metric labels).
    pub const ALL: [ErrorCode; 23] = [
        ErrorCode::UnsupportedVersion,
        ErrorCode::Unauthorized,
        ErrorCode::UnknownDatabase,
        ErrorCode::Forbidden,
        ErrorCode::HelloRequired,
        ErrorCode::Malformed,
        ErrorCode::FrameTooLarge,
        ErrorCode::UnknownMessage,
        ErrorCode::OutOfRange,
        ErrorCode::NotARecord,
        ErrorCode::WrongSize,
        ErrorCode::RecordTooLarge,
        ErrorCode::TooManyInFlight,
        ErrorCode::RateLimited,
        ErrorCode::ServerBusy,
        ErrorCode::CorruptRecord,
        ErrorCode::Cancelled,
        ErrorCode::ShuttingDown,
        ErrorCode::Internal,
        ErrorCode::DuplicateHello,
        ErrorCode::DuplicateRequest,
        ErrorCode::Timeout,
        ErrorCode::Storage,
    ];

    /// The numeric wire value.
    pub const fn as_u16(self) -> u16 {
        self as u16
    }

    /// Parses a numeric wire value; `None` for values this version does not know.
    pub const fn from_u16(value: u16) -> Option<ErrorCode> {
        Some(match value {
            1 => ErrorCode::UnsupportedVersion,
            2 => ErrorCode::Unauthorized,
            3 => ErrorCode::UnknownDatabase,
            4 => ErrorCode::Forbidden,
            5 => ErrorCode::HelloRequired,
            6 => ErrorCode::Malformed,
            7 => ErrorCode::FrameTooLarge,
            8 => ErrorCode::UnknownMessage,
            9 => ErrorCode::OutOfRange,
            10 => ErrorCode::NotARecord,
            11 => ErrorCode::WrongSize,
            12 => ErrorCode::RecordTooLarge,
            13 => ErrorCode::TooManyInFlight,
            14 => ErrorCode::RateLimited,
            15 => ErrorCode::ServerBusy,
            16 => ErrorCode::CorruptRecord,
            17 => ErrorCode::Cancelled,
            18 => ErrorCode::ShuttingDown,
            19 => ErrorCode::Internal,
            20 => ErrorCode::DuplicateHello,
            21 => ErrorCode::DuplicateRequest,
            22 => ErrorCode::Timeout,
            23 => ErrorCode::Storage,
            _ => return None,
        })
    }

    /// Stable snake_case name, usable as a metric label.
    pub const fn as_str(self) -> &'static str {
        match self {
            ErrorCode::UnsupportedVersion => "unsupported_version",
            ErrorCode::Unauthorized => "unauthorized",
            ErrorCode::UnknownDatabase => "unknown_database",
            ErrorCode::Forbidden => "forbidden",
            ErrorCode::HelloRequired => "hello_required",
            ErrorCode::Malformed => "malformed",
            ErrorCode::FrameTooLarge => "frame_too_large",
            ErrorCode::UnknownMessage => "unknown_message",
            ErrorCode::OutOfRange => "out_of_range",
            ErrorCode::NotARecord => "not_a_record",
            ErrorCode::WrongSize => "wrong_size",
            ErrorCode::RecordTooLarge => "record_too_large",
            ErrorCode::TooManyInFlight => "too_many_in_flight",
            ErrorCode::RateLimited => "rate_limited",
            ErrorCode::ServerBusy => "server_busy",
            ErrorCode::CorruptRecord => "corrupt_record",
            ErrorCode::Cancelled => "cancelled",
            ErrorCode::ShuttingDown => "shutting_down",
            ErrorCode::Internal => "internal",
            ErrorCode::DuplicateHello => "duplicate_hello",
            ErrorCode::DuplicateRequest => "duplicate_request",
            ErrorCode::Timeout => "timeout",
            ErrorCode::Storage => "storage",
        }
    }

    /// The code as a QUIC application error code (for `reset`, `stop`, `close`).
    ///
    /// Protocol error codes are used verbatim as QUIC application codes, so a
    /// peer that sees a stream reset or a connection close can map it back with
    /// [`ErrorCode::from_quic`].
    pub const fn to_quic(self) -> u32 {
        self as u32
    }

    /// Maps a QUIC application error code back to an [`ErrorCode`].
    ///
    /// Returns `None` for [`quic::NO_ERROR`] and for unknown values.
    pub fn from_quic(code: u64) -> Option<ErrorCode> {
        u16::try_from(code).ok().and_then(ErrorCode::from_u16)
    }
}

impl fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl TryFrom<u16> for ErrorCode {
    type Error = u16;

    fn try_from(value: u16) -> Result<Self, Self::Error> {
        ErrorCode::from_u16(value).ok_or(value)
    }
}

impl From<ErrorCode> for u16 {
    fn from(code: ErrorCode) -> u16 {
        code.as_u16()
    }
}

impl Encode for ErrorCode {
    fn encode<E: Encoder>(&self, encoder: &mut E) -> Result<(), EncodeError> {
        self.as_u16().encode(encoder)
    }
}

impl<Context> Decode<Context> for ErrorCode {
    fn decode<D: Decoder<Context = Context>>(decoder: &mut D) -> Result<Self, DecodeError> {
        let value = u16::decode(decoder)?;
        ErrorCode::from_u16(value).ok_or(DecodeError::Other("unknown error code"))
    }
}
bincode::impl_borrow_decode!(ErrorCode);

/// QUIC application error codes (the `u32` given to quinn's `VarInt::from_u32`).
///
/// Besides these constants, any [`ErrorCode`] may be used via
/// [`ErrorCode::to_quic`]: e.g. a server that cannot finish a response does
/// `send.reset(ErrorCode::Internal.to_quic())`.
pub mod quic {
    use super::ErrorCode;

    /// No error: normal connection close / stream stop without a reason.
    pub const NO_ERROR: u32 = 0;

    /// The client no longer wants a response: `recv.stop(STREAM_CANCELLED)`
    /// on the request stream. The server's pending write then fails with
    /// `Stopped(STREAM_CANCELLED)`. A server may also `send.reset` with it.
    pub const STREAM_CANCELLED: u32 = ErrorCode::Cancelled.to_quic();

    /// Graceful connection close by either side once it is done.
    pub const CONNECTION_CLOSED_NORMAL: u32 = NO_ERROR;

    /// The server closes connections because it is shutting down.
    pub const CONNECTION_CLOSED_SHUTDOWN: u32 = ErrorCode::ShuttingDown.to_quic();

    /// The server refused the connection (connection limit).
    pub const CONNECTION_CLOSED_BUSY: u32 = ErrorCode::ServerBusy.to_quic();

    /// The connection idled out (no traffic for `idle_timeout_ms`), when closed
    /// explicitly by the application rather than by QUIC's own idle timer.
    pub const CONNECTION_CLOSED_IDLE: u32 = 0x100;

    /// Closing after a protocol violation: use the violated code's value,
    /// e.g. `ErrorCode::Malformed.to_quic()`. This constant is the fallback
    /// when no more specific code applies.
    pub const CONNECTION_CLOSED_PROTOCOL_ERROR: u32 = ErrorCode::Malformed.to_quic();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numeric_values_are_stable() {
        assert_eq!(ErrorCode::UnsupportedVersion as u16, 1);
        assert_eq!(ErrorCode::Unauthorized as u16, 2);
        assert_eq!(ErrorCode::Forbidden as u16, 4);
        assert_eq!(ErrorCode::OutOfRange as u16, 9);
        assert_eq!(ErrorCode::CorruptRecord as u16, 16);
        assert_eq!(ErrorCode::Cancelled as u16, 17);
        assert_eq!(ErrorCode::DuplicateHello as u16, 20);
        assert_eq!(ErrorCode::DuplicateRequest as u16, 21);
        assert_eq!(ErrorCode::Timeout as u16, 22);
        assert_eq!(ErrorCode::Timeout.as_str(), "timeout");
        assert_eq!(ErrorCode::Storage as u16, 23);
    }

    #[test]
    fn all_round_trips_and_is_dense() {
        for (i, code) in ErrorCode::ALL.iter().enumerate() {
            assert_eq!(code.as_u16() as usize, i + 1);
            assert_eq!(ErrorCode::from_u16(code.as_u16()), Some(*code));
            assert_eq!(ErrorCode::from_quic(u64::from(code.to_quic())), Some(*code));
        }
        assert_eq!(ErrorCode::from_u16(0), None);
        assert_eq!(ErrorCode::from_u16(24), None);
        assert_eq!(ErrorCode::from_quic(1 << 20), None);
    }

    #[test]
    fn names_are_unique_snake_case() {
        let mut names: Vec<&str> = ErrorCode::ALL.iter().map(|c| c.as_str()).collect();
        for n in &names {
            assert!(n.chars().all(|c| c.is_ascii_lowercase() || c == '_'), "{n}");
        }
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), ErrorCode::ALL.len());
        assert_eq!(ErrorCode::TooManyInFlight.to_string(), "too_many_in_flight");
    }

    #[test]
    fn quic_constants() {
        assert_eq!(quic::STREAM_CANCELLED, 17);
        assert_eq!(
            ErrorCode::from_quic(quic::STREAM_CANCELLED.into()),
            Some(ErrorCode::Cancelled)
        );
        assert_eq!(ErrorCode::from_quic(quic::NO_ERROR.into()), None);
        assert_eq!(
            ErrorCode::from_quic(quic::CONNECTION_CLOSED_IDLE.into()),
            None
        );
    }
}
