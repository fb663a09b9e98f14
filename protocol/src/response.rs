//! Request streams: one [`LodRequest`] frame (type `LodRequest` or
//! `LodRefsRequest`, [`RequestKind`]) from the client, one [`ResponseHead`]
//! frame plus raw bytes from the server.
//!
//! The body is not bincode-framed: it is exactly `body_len` raw bytes after
//! the head. For a `LodRequest`, `body_len` must equal the requested `size`;
//! for a `LodRefsRequest` it is `size` plus a trailer of at most
//! [`MAX_REFS_TRAILER_LEN`] bytes (the child tables, docs/PROTOCOL.md §4.8).
//! The body is therefore length-prefixed twice (by the request and by the
//! head), so a stream that ends early is always detected as
//! [`ProtocolError::ShortBody`].

use crate::error::ProtocolError;
use crate::frame::{FrameDecoder, MAX_FRAME_LEN};
use crate::message::{
    ErrorMsg, LodRequest, Message, RequestKind, ResponseHead, Status, StreamPriority,
    MAX_REFS_TRAILER_LEN,
};

/// Decodes the whole client side of a request stream (read to its end, at
/// most [`crate::LOD_REQUEST_FRAME_LEN`] bytes): exactly one [`LodRequest`]
/// frame. A `LodRefsRequest` is refused here as an unexpected message; a
/// server that serves both uses [`decode_any_request_stream`].
pub fn decode_request_stream(bytes: &[u8]) -> Result<LodRequest, ProtocolError> {
    match decode_stream(bytes, false, "on a request stream (expected lod_request)")? {
        RequestStream {
            request,
            kind: RequestKind::Record,
            ..
        } => Ok(request),
        RequestStream { kind, .. } => Err(ProtocolError::UnexpectedMessage {
            got: kind.msg_type(),
            context: "on a request stream (expected lod_request)",
        }),
    }
}

/// Decodes the whole client side of a request stream (read to its end, at
/// most [`crate::MAX_REQUEST_FRAME_LEN`] bytes): exactly one `LodRequest`,
/// `LodRefsRequest` or `LodRefsAboveRequest` frame, with the kind of
/// request it is. A `Priority` frame is refused here, as an unexpected
/// message; a server that reads it uses
/// [`decode_prioritized_request_stream`] (and one that turns priorities
/// off answers it as `unknown_message`, as a server that predates it).
pub fn decode_any_request_stream(bytes: &[u8]) -> Result<(LodRequest, RequestKind), ProtocolError> {
    decode_stream(
        bytes,
        false,
        "on a request stream (expected lod_request, lod_refs_request or lod_refs_above_request)",
    )
    .map(|s| (s.request, s.kind))
}

/// The client side of a request stream as a server that knows the
/// `Priority` frame reads it ([`decode_prioritized_request_stream`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct RequestStream {
    /// The request.
    pub request: LodRequest,
    /// The frame type it came in.
    pub kind: RequestKind,
    /// The `Priority` frame before it, if any (docs/PROTOCOL.md §4.10).
    pub priority: Option<StreamPriority>,
}

/// Decodes the whole client side of a request stream (read to its end, at
/// most [`crate::MAX_REQUEST_STREAM_LEN`] bytes): an optional `Priority`
/// frame, then exactly one `LodRequest`, `LodRefsRequest` or
/// `LodRefsAboveRequest` frame.
pub fn decode_prioritized_request_stream(bytes: &[u8]) -> Result<RequestStream, ProtocolError> {
    decode_stream(
        bytes,
        true,
        "on a request stream (expected priority, lod_request, lod_refs_request or lod_refs_above_request)",
    )
}

fn decode_stream(
    bytes: &[u8],
    prioritized: bool,
    context: &'static str,
) -> Result<RequestStream, ProtocolError> {
    let mut dec = FrameDecoder::with_max_frame_len(MAX_FRAME_LEN);
    dec.push(bytes);
    let mut priority = None;
    let (request, kind) = loop {
        match dec.next_frame()? {
            Some(Message::LodRequest(req)) => break (req, RequestKind::Record),
            Some(Message::LodRefsRequest(req)) => break (req, RequestKind::RecordAndRefs),
            Some(Message::LodRefsAboveRequest(r)) => {
                break (r.request(), RequestKind::RecordAndRefsAbove(r.floors))
            }
            // At most one, first.
            Some(Message::Priority(p)) if prioritized && priority.is_none() => priority = Some(p),
            Some(other) => {
                return Err(ProtocolError::UnexpectedMessage {
                    got: other.msg_type(),
                    context,
                })
            }
            None => {
                dec.finish()?;
                return Err(ProtocolError::UnexpectedEnd {
                    during: "before the request frame",
                });
            }
        }
    };
    if dec.buffered() != 0 {
        return Err(ProtocolError::TrailingData {
            extra: dec.buffered() as u64,
            after: "request frame",
        });
    }
    Ok(RequestStream {
        request,
        kind,
        priority,
    })
}

/// A fully received response.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Response {
    /// The record bytes (exactly the requested size; for a `LodRefsRequest`
    /// followed by the trailer of child tables).
    Record {
        /// The request id.
        id: u64,
        /// The raw record bytes.
        body: Vec<u8>,
    },
    /// The server refused or failed the request.
    Error {
        /// The request id.
        id: u64,
        /// Why.
        error: ErrorMsg,
    },
}

#[derive(Debug, Clone)]
enum State {
    Head(FrameDecoder),
    Body { head: ResponseHead, body: Vec<u8> },
    Failed(ProtocolError),
}

/// Incremental decoder for the server side of a request stream, used by the
/// client. Push bytes as they arrive, then call [`ResponseDecoder::finish`]
/// at end of stream.
///
/// It checks that the head's id matches the request, that a successful
/// head's `body_len` equals the requested `size` (is within `size ..= size +`
/// [`MAX_REFS_TRAILER_LEN`] for a `LodRefsRequest`), that no byte follows the
/// body, and (in `finish`) that the body is complete.
#[derive(Debug, Clone)]
pub struct ResponseDecoder {
    request: LodRequest,
    kind: RequestKind,
    state: State,
}

impl ResponseDecoder {
    /// A decoder for the response to `request` sent as a `LodRequest`.
    pub fn new(request: LodRequest) -> Self {
        ResponseDecoder::for_kind(request, RequestKind::Record)
    }

    /// A decoder for the response to `request` sent as a `LodRefsRequest`:
    /// a successful body is the record (`size` bytes) then a trailer of at
    /// most [`MAX_REFS_TRAILER_LEN`] bytes.
    pub fn with_refs(request: LodRequest) -> Self {
        ResponseDecoder::for_kind(request, RequestKind::RecordAndRefs)
    }

    /// A decoder for the response to `request` sent as a request of `kind`.
    pub fn for_kind(request: LodRequest, kind: RequestKind) -> Self {
        ResponseDecoder {
            request,
            kind,
            state: State::Head(FrameDecoder::with_max_frame_len(MAX_FRAME_LEN)),
        }
    }

    /// The request this decoder expects a response to.
    pub fn request(&self) -> &LodRequest {
        &self.request
    }

    /// The kind of request this decoder expects a response to.
    pub fn kind(&self) -> RequestKind {
        self.kind
    }

    /// The head, once received.
    pub fn head(&self) -> Option<&ResponseHead> {
        match &self.state {
            State::Body { head, .. } => Some(head),
            _ => None,
        }
    }

    /// Body bytes still expected (`None` until the head has arrived).
    pub fn remaining_body(&self) -> Option<u32> {
        match &self.state {
            State::Body { head, body } => Some(head.body_len - body.len() as u32),
            _ => None,
        }
    }

    /// True once the head and the whole body have arrived.
    pub fn is_complete(&self) -> bool {
        self.remaining_body() == Some(0)
    }

    /// Feeds received bytes. Fails on a malformed or mismatched head and on
    /// bytes past the end of the body; the decoder then stays failed.
    pub fn push(&mut self, bytes: &[u8]) -> Result<(), ProtocolError> {
        let result = self.push_inner(bytes);
        if let Err(e) = &result {
            self.state = State::Failed(e.clone());
        }
        result
    }

    fn push_inner(&mut self, mut bytes: &[u8]) -> Result<(), ProtocolError> {
        if let State::Head(dec) = &mut self.state {
            dec.push(bytes);
            bytes = &[];
            let Some(msg) = dec.next_frame()? else {
                return Ok(());
            };
            let head = match msg {
                Message::ResponseHead(head) => head,
                other => {
                    return Err(ProtocolError::UnexpectedMessage {
                        got: other.msg_type(),
                        context: "on a request stream (expected response_head)",
                    })
                }
            };
            check_head_kind(&self.request, self.kind, &head)?;
            let rest = dec.take_buffered();
            let mut body = Vec::with_capacity(head.body_len as usize);
            append_body(&head, &mut body, &rest)?;
            self.state = State::Body { head, body };
        }
        match &mut self.state {
            State::Body { head, body } => append_body(head, body, bytes),
            State::Failed(e) => Err(e.clone()),
            State::Head(_) => Ok(()),
        }
    }

    /// Call at end of stream: returns the response, or an error if the head
    /// or the body is incomplete.
    pub fn finish(self) -> Result<Response, ProtocolError> {
        match self.state {
            State::Failed(e) => Err(e),
            State::Head(dec) => {
                dec.finish()?;
                Err(ProtocolError::UnexpectedEnd {
                    during: "before the response head",
                })
            }
            State::Body { head, body } => {
                if body.len() != head.body_len as usize {
                    return Err(ProtocolError::ShortBody {
                        expected: head.body_len,
                        received: body.len() as u64,
                    });
                }
                Ok(match head.status {
                    Status::Ok => Response::Record { id: head.id, body },
                    Status::Error(error) => Response::Error { id: head.id, error },
                })
            }
        }
    }
}

/// Decodes a whole response stream (read to its end) to `request`.
pub fn decode_response(request: &LodRequest, stream: &[u8]) -> Result<Response, ProtocolError> {
    let mut dec = ResponseDecoder::new(*request);
    dec.push(stream)?;
    dec.finish()
}

/// Decodes a whole response stream (read to its end) to `request` sent as a
/// `LodRefsRequest` ([`ResponseDecoder::with_refs`]).
pub fn decode_response_with_refs(
    request: &LodRequest,
    stream: &[u8],
) -> Result<Response, ProtocolError> {
    let mut dec = ResponseDecoder::with_refs(*request);
    dec.push(stream)?;
    dec.finish()
}

/// Checks a response head against its request (sent as a `LodRequest`).
pub fn check_head(request: &LodRequest, head: &ResponseHead) -> Result<(), ProtocolError> {
    check_head_kind(request, RequestKind::Record, head)
}

/// Checks a response head against its request sent as a request of `kind`:
/// the id, and on `Ok` a `body_len` of `size` (plus at most
/// [`RequestKind::max_trailer_len`]).
pub fn check_head_kind(
    request: &LodRequest,
    kind: RequestKind,
    head: &ResponseHead,
) -> Result<(), ProtocolError> {
    if head.id != request.id {
        return Err(ProtocolError::ResponseIdMismatch {
            expected: request.id,
            got: head.id,
        });
    }
    if head.status != Status::Ok {
        return Ok(());
    }
    match kind {
        RequestKind::Record if head.body_len != request.size => {
            Err(ProtocolError::BodyLengthMismatch {
                expected: request.size,
                got: head.body_len,
            })
        }
        RequestKind::RecordAndRefs | RequestKind::RecordAndRefsAbove(_) => {
            let max = u64::from(request.size) + u64::from(MAX_REFS_TRAILER_LEN);
            if head.body_len < request.size || u64::from(head.body_len) > max {
                Err(ProtocolError::BodyLengthOutOfRange {
                    min: request.size,
                    max,
                    got: head.body_len,
                })
            } else {
                Ok(())
            }
        }
        RequestKind::Record => Ok(()),
    }
}

fn append_body(head: &ResponseHead, body: &mut Vec<u8>, bytes: &[u8]) -> Result<(), ProtocolError> {
    let room = head.body_len as usize - body.len();
    if bytes.len() > room {
        return Err(ProtocolError::TrailingData {
            extra: (bytes.len() - room) as u64,
            after: "response body",
        });
    }
    body.extend_from_slice(bytes);
    Ok(())
}
