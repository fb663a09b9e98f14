//! Protocol frames from an untrusted peer: the frame decoder fed in arbitrary
//! fragments, the request-stream decoder and the response decoder.
#![no_main]
use libfuzzer_sys::fuzz_target;
use planet_protocol::{decode_request_stream, FrameDecoder, LodRequest, ResponseDecoder};

fuzz_target!(|data: &[u8]| {
    // Split at a data-dependent point so fragmented delivery is explored.
    let cut = data.first().map_or(0, |b| *b as usize % (data.len() + 1));
    let mut dec = FrameDecoder::new();
    dec.push(&data[..cut]);
    while let Ok(Some(_)) = dec.next_frame() {}
    dec.push(&data[cut..]);
    while let Ok(Some(_)) = dec.next_frame() {}
    let _ = dec.finish();

    let _ = decode_request_stream(data);

    let req = LodRequest { id: 7, offset: 64, size: 100 };
    let mut resp = ResponseDecoder::new(req);
    let _ = resp.push(data);
    let _ = resp.finish();
});
