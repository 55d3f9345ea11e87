//! Fuzz the client's decoder of server messages: never panic; whatever is accepted re-encodes to itself.
#![no_main]

use canopy_protocol::ServerMsg;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(msg) = ServerMsg::decode(data) {
        let again = msg.encode();
        assert_eq!(ServerMsg::decode(&again).as_ref(), Ok(&msg));
    }
});
