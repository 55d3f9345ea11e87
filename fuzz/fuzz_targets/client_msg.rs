//! Fuzz the server's decoder of client messages: never panic; whatever is accepted re-encodes to itself.
#![no_main]

use canopy_protocol::ClientMsg;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(msg) = ClientMsg::decode(data) {
        let again = msg.encode();
        assert_eq!(ClientMsg::decode(&again).as_ref(), Ok(&msg));
        assert!(again.len() <= canopy_protocol::netlimits::MAX_CLIENT_FRAME);
    }
});
