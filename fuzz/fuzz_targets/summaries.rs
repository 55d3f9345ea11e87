//! Fuzz the client's decoder of far-view summaries (the bytes after a summaries message's tags): never panic;
//! whatever is accepted re-encodes to itself and stays within a server frame.
#![no_main]

use canopy_protocol::ServerMsg;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // `ServerMsg::Streaming` (1), `ServerStreaming::Summaries` (6), then the batch.
    let mut bytes = vec![0x01, 0x06];
    bytes.extend_from_slice(data);
    if let Ok(msg) = ServerMsg::decode(&bytes) {
        let again = msg.encode();
        assert_eq!(ServerMsg::decode(&again).as_ref(), Ok(&msg));
        assert!(again.len() <= canopy_protocol::netlimits::MAX_SERVER_FRAME);
    }
});
