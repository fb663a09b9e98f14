//! Framing: how messages are delimited on a QUIC stream.
//!
//! ```text
//! +----------------+---------+---------------------------+
//! | len: u32 LE    | type u8 | body (len - 1 bytes)      |
//! +----------------+---------+---------------------------+
//! ```
//!
//! `len` counts the type byte and the body (not itself), so it is at least 1.
//! It is checked against [`MessageType::max_frame_len`] as soon as the type
//! byte is known, and against the decoder's own cap as soon as the prefix is
//! known, before any body byte is buffered.
//!
//! Raw record bytes following a [`crate::ResponseHead`] are *not* frames; use
//! [`crate::ResponseDecoder`] on request streams.

use std::fmt;

use crate::codec;
use crate::error::ProtocolError;
use crate::message::{
    Cancel, ErrorMsg, Goodbye, Hello, LodRefsAboveRequest, LodRequest, Message, ResponseHead,
    StreamPriority, Welcome, WireBody, MAX_HEADER_LEN,
};

/// Size of the length prefix.
pub const LEN_PREFIX_LEN: usize = 4;

/// Size of the length prefix plus the type byte.
pub const FRAME_HEADER_LEN: usize = LEN_PREFIX_LEN + 1;

/// Largest frame length (`len` field: type byte + body) for every message
/// except [`Welcome`].
pub const MAX_FRAME_LEN: u32 = 64 * 1024;

/// Largest frame length for a [`Welcome`], which carries the database header.
pub const MAX_WELCOME_FRAME_LEN: u32 = MAX_HEADER_LEN as u32 + MAX_FRAME_LEN;

/// Exact size on the wire of a [`LodRequest`] frame, prefix included: a
/// server can read a request stream to its end with this limit. A
/// `LodRefsRequest` frame ([`Message::LodRefsRequest`]) has the same body
/// and the same size.
pub const LOD_REQUEST_FRAME_LEN: usize = FRAME_HEADER_LEN + 8 + 8 + 4;

/// Exact size on the wire of a `LodRefsAboveRequest` frame
/// ([`LodRefsAboveRequest`]), prefix included: a `LodRequest` body and four
/// `f32` floors.
pub const LOD_REFS_ABOVE_REQUEST_FRAME_LEN: usize = LOD_REQUEST_FRAME_LEN + 4 * 4;

/// The longest request frame.
pub const MAX_REQUEST_FRAME_LEN: usize = LOD_REFS_ABOVE_REQUEST_FRAME_LEN;

/// Exact size on the wire of a `Priority` frame ([`StreamPriority`]),
/// prefix included: one `i32`.
pub const PRIORITY_FRAME_LEN: usize = FRAME_HEADER_LEN + 4;

/// The longest client side of a request stream, a `Priority` frame and the
/// longest request frame: a server reads a request stream to its end with
/// this limit.
pub const MAX_REQUEST_STREAM_LEN: usize = PRIORITY_FRAME_LEN + MAX_REQUEST_FRAME_LEN;

/// Exact size on the wire of a successful [`ResponseHead`] frame, prefix included.
pub const RESPONSE_HEAD_OK_FRAME_LEN: usize = FRAME_HEADER_LEN + 8 + 4 + 4;

/// The type byte of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u8)]
pub enum MessageType {
    /// [`Hello`], client -> server, control stream.
    Hello = 0x01,
    /// [`Welcome`], server -> client, control stream.
    Welcome = 0x02,
    /// [`ErrorMsg`], either direction, control stream.
    Error = 0x03,
    /// [`Goodbye`], either direction, control stream.
    Goodbye = 0x04,
    /// [`Cancel`], client -> server, control stream.
    Cancel = 0x05,
    /// [`LodRequest`], client -> server, request stream.
    LodRequest = 0x10,
    /// [`ResponseHead`], server -> client, request stream.
    ResponseHead = 0x11,
    /// [`Message::LodRefsRequest`] (a [`LodRequest`] body), client -> server,
    /// request stream: the record, then its children's child tables.
    LodRefsRequest = 0x12,
    /// [`LodRefsAboveRequest`], client -> server, request stream: the
    /// record, then the child tables that reach their floors.
    LodRefsAboveRequest = 0x13,
    /// [`StreamPriority`], client -> server, request stream, before the
    /// request frame: the order in which the server sends its response.
    Priority = 0x14,
}

impl MessageType {
    /// Every message type.
    pub const ALL: [MessageType; 10] = [
        MessageType::Hello,
        MessageType::Welcome,
        MessageType::Error,
        MessageType::Goodbye,
        MessageType::Cancel,
        MessageType::LodRequest,
        MessageType::ResponseHead,
        MessageType::LodRefsRequest,
        MessageType::LodRefsAboveRequest,
        MessageType::Priority,
    ];

    /// Parses a type byte.
    pub const fn from_u8(byte: u8) -> Option<MessageType> {
        Some(match byte {
            0x01 => MessageType::Hello,
            0x02 => MessageType::Welcome,
            0x03 => MessageType::Error,
            0x04 => MessageType::Goodbye,
            0x05 => MessageType::Cancel,
            0x10 => MessageType::LodRequest,
            0x11 => MessageType::ResponseHead,
            0x12 => MessageType::LodRefsRequest,
            0x13 => MessageType::LodRefsAboveRequest,
            0x14 => MessageType::Priority,
            _ => return None,
        })
    }

    /// The type byte.
    pub const fn as_u8(self) -> u8 {
        self as u8
    }

    /// The largest allowed `len` for frames of this type.
    pub const fn max_frame_len(self) -> u32 {
        match self {
            MessageType::Welcome => MAX_WELCOME_FRAME_LEN,
            _ => MAX_FRAME_LEN,
        }
    }

    /// A stable snake_case name (for logs and metric labels).
    pub const fn as_str(self) -> &'static str {
        match self {
            MessageType::Hello => "hello",
            MessageType::Welcome => "welcome",
            MessageType::Error => "error",
            MessageType::Goodbye => "goodbye",
            MessageType::Cancel => "cancel",
            MessageType::LodRequest => "lod_request",
            MessageType::ResponseHead => "response_head",
            MessageType::LodRefsRequest => "lod_refs_request",
            MessageType::LodRefsAboveRequest => "lod_refs_above_request",
            MessageType::Priority => "priority",
        }
    }
}

impl fmt::Display for MessageType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Appends one frame holding `msg` to `out`. On error `out` is left unchanged.
pub fn encode_frame_into(msg: &Message, out: &mut Vec<u8>) -> Result<(), ProtocolError> {
    match msg {
        Message::Hello(m) => encode_body_frame(m, out),
        Message::Welcome(m) => encode_body_frame(m, out),
        Message::Error(m) => encode_body_frame(m, out),
        Message::Goodbye(m) => encode_body_frame(m, out),
        Message::Cancel(m) => encode_body_frame(m, out),
        Message::LodRequest(m) => encode_body_frame(m, out),
        Message::ResponseHead(m) => encode_body_frame(m, out),
        Message::LodRefsRequest(m) => encode_body_frame_as(m, MessageType::LodRefsRequest, out),
        Message::LodRefsAboveRequest(m) => encode_body_frame(m, out),
        Message::Priority(m) => encode_body_frame(m, out),
    }
}

/// Encodes one frame holding `msg` into a new buffer.
pub fn encode_frame(msg: &Message) -> Result<Vec<u8>, ProtocolError> {
    let mut out = Vec::new();
    encode_frame_into(msg, &mut out)?;
    Ok(out)
}

pub(crate) fn encode_body_frame<T: WireBody>(
    body: &T,
    out: &mut Vec<u8>,
) -> Result<(), ProtocolError> {
    encode_body_frame_as(body, T::TYPE, out)
}

/// [`encode_body_frame`] under another type byte than the body's own (a
/// `LodRefsRequest` frame carries a [`LodRequest`] body).
pub(crate) fn encode_body_frame_as<T: WireBody>(
    body: &T,
    msg_type: MessageType,
    out: &mut Vec<u8>,
) -> Result<(), ProtocolError> {
    body.check()?;
    let start = out.len();
    out.extend_from_slice(&[0; LEN_PREFIX_LEN]);
    out.push(msg_type.as_u8());
    if let Err(e) = codec::encode_into(body, msg_type, out) {
        out.truncate(start);
        return Err(e);
    }
    let len = out.len() - start - LEN_PREFIX_LEN;
    let max = msg_type.max_frame_len();
    if len > max as usize {
        out.truncate(start);
        return Err(ProtocolError::FrameTooLarge {
            len: len as u64,
            max,
        });
    }
    // `len <= max <= u32::MAX` was just checked.
    let len = len as u32;
    out[start..start + LEN_PREFIX_LEN].copy_from_slice(&len.to_le_bytes());
    Ok(())
}

/// Where the next frame in a buffer stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FrameStart {
    /// Not enough bytes to know; `Some(total)` once the prefix is known.
    Incomplete(Option<usize>),
    /// A complete frame of `total` bytes (prefix included) of this type.
    Complete(MessageType, usize),
}

/// Validates the frame header at the start of `buf`.
fn frame_start(buf: &[u8], cap: u32) -> Result<FrameStart, ProtocolError> {
    let Some(prefix) = buf.first_chunk::<LEN_PREFIX_LEN>() else {
        return Ok(FrameStart::Incomplete(None));
    };
    let len = u32::from_le_bytes(*prefix);
    if len == 0 {
        return Err(ProtocolError::EmptyFrame);
    }
    if len > cap {
        return Err(ProtocolError::FrameTooLarge {
            len: len.into(),
            max: cap,
        });
    }
    let total = LEN_PREFIX_LEN + len as usize;
    let Some(&type_byte) = buf.get(LEN_PREFIX_LEN) else {
        return Ok(FrameStart::Incomplete(Some(total)));
    };
    let msg_type =
        MessageType::from_u8(type_byte).ok_or(ProtocolError::UnknownMessageType(type_byte))?;
    if len > msg_type.max_frame_len() {
        return Err(ProtocolError::FrameTooLarge {
            len: len.into(),
            max: msg_type.max_frame_len(),
        });
    }
    if buf.len() < total {
        Ok(FrameStart::Incomplete(Some(total)))
    } else {
        Ok(FrameStart::Complete(msg_type, total))
    }
}

fn decode_body(msg_type: MessageType, body: &[u8]) -> Result<Message, ProtocolError> {
    const CONTROL: usize = MAX_FRAME_LEN as usize;
    const WELCOME: usize = MAX_WELCOME_FRAME_LEN as usize;
    let msg: Message = match msg_type {
        MessageType::Hello => codec::decode_exact::<Hello, CONTROL>(body, msg_type)?.into(),
        MessageType::Welcome => codec::decode_exact::<Welcome, WELCOME>(body, msg_type)?.into(),
        MessageType::Error => codec::decode_exact::<ErrorMsg, CONTROL>(body, msg_type)?.into(),
        MessageType::Goodbye => codec::decode_exact::<Goodbye, CONTROL>(body, msg_type)?.into(),
        MessageType::Cancel => codec::decode_exact::<Cancel, CONTROL>(body, msg_type)?.into(),
        MessageType::LodRequest => {
            codec::decode_exact::<LodRequest, CONTROL>(body, msg_type)?.into()
        }
        MessageType::ResponseHead => {
            codec::decode_exact::<ResponseHead, CONTROL>(body, msg_type)?.into()
        }
        MessageType::LodRefsRequest => {
            Message::LodRefsRequest(codec::decode_exact::<LodRequest, CONTROL>(body, msg_type)?)
        }
        MessageType::LodRefsAboveRequest => {
            codec::decode_exact::<LodRefsAboveRequest, CONTROL>(body, msg_type)?.into()
        }
        MessageType::Priority => {
            codec::decode_exact::<StreamPriority, CONTROL>(body, msg_type)?.into()
        }
    };
    msg.validate()?;
    Ok(msg)
}

/// Decodes the frame at the start of `buf`, with the per-type limits only.
///
/// Returns `Ok(None)` if `buf` does not hold a complete frame yet, otherwise
/// the message and the number of bytes it occupied.
pub fn decode_frame(buf: &[u8]) -> Result<Option<(Message, usize)>, ProtocolError> {
    decode_frame_capped(buf, MAX_WELCOME_FRAME_LEN)
}

fn decode_frame_capped(buf: &[u8], cap: u32) -> Result<Option<(Message, usize)>, ProtocolError> {
    match frame_start(buf, cap)? {
        FrameStart::Incomplete(_) => Ok(None),
        FrameStart::Complete(msg_type, total) => {
            let msg = decode_body(msg_type, &buf[FRAME_HEADER_LEN..total])?;
            Ok(Some((msg, total)))
        }
    }
}

/// Incremental frame decoder: push bytes as they arrive, pull messages out.
///
/// After an error the decoder is poisoned: every later call to
/// [`FrameDecoder::next_frame`] returns the same error (the stream cannot be
/// resynchronised).
///
/// ```
/// use planet_protocol::{Cancel, FrameDecoder, Message};
/// let bytes = Cancel { id: 7 }.encode_frame().unwrap();
/// let mut dec = FrameDecoder::new();
/// dec.push(&bytes[..3]);
/// assert_eq!(dec.next_frame().unwrap(), None);
/// dec.push(&bytes[3..]);
/// assert_eq!(dec.next_frame().unwrap(), Some(Message::Cancel(Cancel { id: 7 })));
/// dec.finish().unwrap();
/// ```
#[derive(Debug, Clone)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    cap: u32,
    failed: Option<ProtocolError>,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        FrameDecoder::new()
    }
}

impl FrameDecoder {
    /// A decoder that applies only the per-type limits
    /// ([`MessageType::max_frame_len`]).
    pub fn new() -> Self {
        FrameDecoder::with_max_frame_len(MAX_WELCOME_FRAME_LEN)
    }

    /// A decoder that also rejects any frame whose `len` exceeds `max`
    /// (a server uses [`MAX_FRAME_LEN`]: it never receives a `Welcome`).
    pub fn with_max_frame_len(max: u32) -> Self {
        FrameDecoder {
            buf: Vec::new(),
            cap: max,
            failed: None,
        }
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.failed.is_none() {
            self.buf.extend_from_slice(bytes);
        }
    }

    /// Decodes the next complete frame, if any.
    ///
    /// Errors are reported as soon as they are detectable: an oversized or
    /// unknown frame is rejected from its 5-byte header, before its body
    /// arrives.
    pub fn next_frame(&mut self) -> Result<Option<Message>, ProtocolError> {
        if let Some(e) = &self.failed {
            return Err(e.clone());
        }
        match decode_frame_capped(&self.buf, self.cap) {
            Ok(Some((msg, used))) => {
                self.buf.drain(..used);
                Ok(Some(msg))
            }
            Ok(None) => Ok(None),
            Err(e) => {
                self.failed = Some(e.clone());
                self.buf = Vec::new();
                Err(e)
            }
        }
    }

    /// Number of buffered bytes not yet returned as frames.
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Call at end of stream: fails with [`ProtocolError::Truncated`] if a
    /// partial frame is buffered (or with the earlier error if the decoder
    /// failed). Drain complete frames with [`FrameDecoder::next_frame`] first:
    /// an undrained complete frame is reported as
    /// [`ProtocolError::TrailingData`].
    pub fn finish(&self) -> Result<(), ProtocolError> {
        if let Some(e) = &self.failed {
            return Err(e.clone());
        }
        if self.buf.is_empty() {
            return Ok(());
        }
        match frame_start(&self.buf, self.cap)? {
            FrameStart::Incomplete(expected) => Err(ProtocolError::Truncated {
                buffered: self.buf.len(),
                expected,
            }),
            FrameStart::Complete(..) => Err(ProtocolError::TrailingData {
                extra: self.buf.len() as u64,
                after: "last decoded frame",
            }),
        }
    }

    /// Removes and returns the buffered bytes that were not decoded yet.
    pub fn take_buffered(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.buf)
    }
}
