//! What the wire tests share: the byte-snapshot checks.

use canopy_protocol::{ClientMsg, ServerMsg};

/// Lowercase hexadecimal.
pub(crate) fn hex(b: &[u8]) -> String {
    b.iter().map(|b| format!("{b:02x}")).collect()
}

/// The snapshot check: the encoding is pinned, and it decodes back to the message.
pub(crate) fn check_client(msg: &ClientMsg, expected: &str) {
    let bytes = msg.encode();
    assert_eq!(hex(&bytes), expected, "the wire form of {} changed; bump PROTOCOL_VERSION if intended", msg.name());
    assert_eq!(ClientMsg::decode(&bytes).as_ref(), Ok(msg));
}

/// [`check_client`] for a server message.
pub(crate) fn check_server(msg: &ServerMsg, expected: &str) {
    let bytes = msg.encode();
    assert_eq!(hex(&bytes), expected, "the wire form of {} changed; bump PROTOCOL_VERSION if intended", msg.name());
    assert_eq!(ServerMsg::decode(&bytes).as_ref(), Ok(msg));
}
