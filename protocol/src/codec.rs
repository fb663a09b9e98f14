//! The single place where the body serialization library is used.
//!
//! Message bodies are encoded with **bincode 2.0.1** (pinned `=2.0.1`) using
//! `bincode::config::standard()` switched to **little-endian, fixed-width
//! integers**: every integer is written at its natural width in LE byte order,
//! and strings / byte vectors are a `u64` LE length followed by the bytes.
//! Enums (only [`crate::Status`]) are a `u32` LE variant index followed by the
//! variant's fields. `docs/PROTOCOL.md` spells the layout out byte by byte.
//!
//! **Maintenance note:** bincode is unmaintained (RUSTSEC-2025-0141, and
//! 3.0.0 is a `compile_error!` stub). It is isolated in this module (plus the
//! `Encode`/`Decode` derives on the message structs) so it can be replaced by
//! a hand-written codec producing the same bytes; the byte-exact test in
//! `tests/wire.rs` pins the format so such a swap can be verified.
//!
//! Decoding always runs with a byte limit so that a length prefix inside a
//! body can never make the decoder allocate more than the frame limit.

use bincode::config::{Configuration, Fixint, LittleEndian};
use bincode::{Decode, Encode};

use crate::error::ProtocolError;
use crate::frame::MessageType;

/// The encoding configuration, without a decode limit.
const fn base() -> Configuration<LittleEndian, Fixint> {
    bincode::config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
}

/// Appends the encoding of `value` to `out`.
pub(crate) fn encode_into<T: Encode>(
    value: &T,
    msg_type: MessageType,
    out: &mut Vec<u8>,
) -> Result<(), ProtocolError> {
    bincode::encode_into_std_write(value, out, base()).map_err(|e| ProtocolError::Encode {
        msg_type,
        reason: e.to_string(),
    })?;
    Ok(())
}

/// Decodes a `T` that must occupy the whole of `body`.
///
/// `LIMIT` bounds the total number of bytes the decoder may claim for
/// variable-length fields (it must be at least the largest valid body).
pub(crate) fn decode_exact<T: Decode<()>, const LIMIT: usize>(
    body: &[u8],
    msg_type: MessageType,
) -> Result<T, ProtocolError> {
    let config = base().with_limit::<LIMIT>();
    let (value, used) =
        bincode::decode_from_slice::<T, _>(body, config).map_err(|e| ProtocolError::Malformed {
            msg_type,
            reason: e.to_string(),
        })?;
    if used != body.len() {
        return Err(ProtocolError::Malformed {
            msg_type,
            reason: format!("{} trailing bytes after the body", body.len() - used),
        });
    }
    Ok(value)
}
