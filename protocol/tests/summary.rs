//! Far-view summaries on the wire (issue 15): byte snapshots of the far view and the summaries message, round
//! trips, bounds, and mutated bytes that must never panic a decoder.

use crate::wire::{check_client, check_server};
use canopy_protocol::messages::{ClientStreaming, ServerStreaming};
use canopy_protocol::summary::{
    FarView, MAX_BATCH_NODES, MAX_NODE_SPECIES, NodeKey, NodeSummary, SpeciesCover, SummaryBatch,
};
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{ClientMsg, MessageError, ServerMsg};

fn far_view() -> FarView {
    FarView { error_px: 16.0, height_px: 1080, fov_y: 1.0, range: 20_000.0, altitude: 1500.0 }
}

fn node() -> NodeSummary {
    NodeSummary {
        key: NodeKey { level: 3, x: -2, z: 5 },
        error: 64.0,
        species: vec![
            SpeciesCover { species: 0, count: 1234, height_dm: 170, spread_dm: 40, cover: 0xffff_0000_ffff_0000 },
            SpeciesCover { species: 3, count: 7, height_dm: 0, spread_dm: 0, cover: 1 },
        ],
    }
}

fn batch() -> SummaryBatch {
    SummaryBatch { nodes: vec![node()], released: vec![NodeKey { level: 0, x: 1, z: -1 }] }
}

#[test]
fn far_view_is_pinned() {
    check_client(
        &ClientMsg::Streaming(ClientStreaming::FarView(far_view())),
        "010400008041b8080000803f00409c460080bb44",
    );
}

#[test]
fn summaries_are_pinned() {
    check_server(
        &ServerMsg::Streaming(ServerStreaming::Summaries(batch())),
        "01060103030a000080420200d209aa01288080fcff8f80c0ffff01030700000101000201",
    );
}

#[test]
fn a_typical_forest_node_is_tens_of_bytes() {
    let bytes = postcard::to_allocvec(&node()).unwrap();
    assert!(bytes.len() <= 40, "{} bytes", bytes.len());
}

#[test]
fn out_of_bounds_summaries_are_refused() {
    let refused = |b: SummaryBatch| {
        let bytes = ServerMsg::Streaming(ServerStreaming::Summaries(b)).encode();
        assert!(matches!(ServerMsg::decode(&bytes), Err(MessageError::Summary(_))), "accepted");
    };
    refused(SummaryBatch { nodes: vec![node(); MAX_BATCH_NODES + 1], released: vec![] });
    let mut n = node();
    n.species = (0..=MAX_NODE_SPECIES as u16)
        .map(|s| SpeciesCover { species: s, count: 1, height_dm: 0, spread_dm: 0, cover: 1 })
        .collect();
    refused(SummaryBatch { nodes: vec![n], released: vec![] });
    let mut n = node();
    n.species.reverse();
    refused(SummaryBatch { nodes: vec![n], released: vec![] });
    refused(SummaryBatch { nodes: vec![], released: vec![NodeKey { level: 30, x: 0, z: 0 }] });
    let far = |v: FarView| ClientMsg::decode(&ClientMsg::Streaming(ClientStreaming::FarView(v)).encode());
    assert!(far(FarView { fov_y: f32::NAN, ..far_view() }).is_err());
    assert!(far(FarView { range: 1.0e6, ..far_view() }).is_err());
    assert!(far(FarView { height_px: 0, ..far_view() }).is_err());
}

#[test]
fn mutated_summaries_never_panic() {
    let mut x = XorShift64::new(0x5eed);
    let base = ServerMsg::Streaming(ServerStreaming::Summaries(batch())).encode();
    let view = ClientMsg::Streaming(ClientStreaming::FarView(far_view())).encode();
    for _ in 0..20_000 {
        for (src, client) in [(&base, false), (&view, true)] {
            let mut b = src.clone();
            for _ in 0..1 + x.next() % 3 {
                let i = (x.next() as usize) % b.len();
                b[i] = x.next() as u8;
            }
            if client {
                if let Ok(m) = ClientMsg::decode(&b) {
                    assert_eq!(ClientMsg::decode(&m.encode()), Ok(m));
                }
            } else if let Ok(m) = ServerMsg::decode(&b) {
                assert_eq!(ServerMsg::decode(&m.encode()), Ok(m));
            }
        }
    }
}
