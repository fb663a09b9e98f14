//! Tokens never appear in `Debug` output: not of a `Hello`, not of the
//! client handshake state that holds one, not of a decoded message.

use planet_protocol::{ClientHandshake, Hello, Message};

const SECRET: &str = "q3Zr8v+Kx1LmPa0TbYw7nE2c";

#[test]
fn hello_and_handshake_state_do_not_print_the_token() {
    let hello = Hello::new("acme", SECRET, "earth");
    let shown = format!("{hello:?} {hello:#?}");
    assert!(!shown.contains(SECRET), "{shown}");
    assert!(shown.contains("acme") && shown.contains("<redacted>"));
    let (hs, frame) = ClientHandshake::new(hello.clone()).unwrap();
    let shown = format!("{hs:?}");
    assert!(!shown.contains(SECRET), "{shown}");
    let mut dec = planet_protocol::FrameDecoder::new();
    dec.push(&frame);
    let msg: Message = dec.next_frame().unwrap().unwrap();
    assert_eq!(msg, Message::Hello(hello));
    let shown = format!("{msg:?}");
    assert!(!shown.contains(SECRET), "{shown}");
}
