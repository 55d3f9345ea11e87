//! Fuzz the species graph decoder (the largest message payload): never panic, accept only valid graphs.
#![no_main]

use canopy_protocol::SpeciesGraph;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(g) = SpeciesGraph::decode(data) {
        assert_eq!(g.validate(), Ok(()));
        assert_eq!(SpeciesGraph::decode(&g.encode()), Ok(g));
    }
});
