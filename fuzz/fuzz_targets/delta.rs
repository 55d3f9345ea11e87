//! Fuzz the client's handling of server messages after a welcome (cell batches, deltas, releases in any order):
//! never panic; an error is a clean refusal.
#![no_main]

use canopy_client::state::ClientState;
use canopy_protocol::ServerMsg;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut state = ClientState::new();
    let mut frames = data.split(|&b| b == 0xff);
    let Some(welcome) = frames.next().and_then(|f| ServerMsg::decode(f).ok()) else { return };
    if state.hello("fuzz").is_err() || state.on_welcome(welcome).is_err() {
        return;
    }
    let vp = canopy_protocol::aoi::Viewpoint::at(1, [0.0, 0.0], 200.0);
    if state.ready(vp).is_err() {
        return;
    }
    for f in frames {
        if let Ok(m) = ServerMsg::decode(f) {
            let _ = state.handle(m);
        }
    }
    let _ = state.instances(&|_, _| 0.0).count();
});
