//! The browser driver against a scripted server: the handshake as `Connection::handshake` does it, lanes split
//! anywhere, cells expanded a bounded number at a time and equal to the world function's, faults closing with a
//! code.

use canopy_protocol::aoi::{Aoi, AoiParams};
use canopy_protocol::messages::{
    CellGrant, ClientHandshake, ClientStreaming, ServerHandshake, SpeciesData, SpeciesEntry, TerrainDesc,
    WorldFunction, WorldInfo,
};
use canopy_protocol::{POSITION_STEPS, PROTOCOL_VERSION};

use super::*;
use crate::page::{PageState, held_digest, world_digest};

const MANIFEST: &str = "seed 7\nbounds -128 -128 128 128\ncell 32\nspecies a worm\nscatter a {\n  spacing 4\n}\n";

fn worm() -> Vec<u8> {
    canopy_worlds::library::find("worm").unwrap().load().unwrap().encode()
}

fn grid() -> Grid {
    Grid { origin: [0.0, 0.0], cell_size: 32.0, min: CellCoord::new(-4, -4), max: CellCoord::new(3, 3) }
}

fn params() -> AoiParams {
    AoiParams { max_radius: 200.0, hysteresis: 16.0, lookahead_s: 0.0, max_lookahead: 0.0 }
}

fn welcome() -> ServerMsg {
    let f = WorldFunction { manifest: MANIFEST.into() };
    let w = Welcome {
        version: PROTOCOL_VERSION,
        world: WorldInfo {
            name: "t".into(),
            seed: 7,
            grid: grid(),
            position_steps: POSITION_STEPS,
            instances: 0,
            terrain: TerrainDesc::flat([-128.0, -128.0], 256.0),
            function: Some(f.hash()),
        },
        species: vec![SpeciesEntry { hash: SpeciesHash::of(&worm()), size: worm().len() as u32 }],
        aoi: params(),
    };
    ServerMsg::Handshake(ServerHandshake::Welcome(w))
}

fn streaming(msg: ServerStreaming) -> Vec<u8> {
    ServerMsg::Streaming(msg).encode_framed()
}

/// The client messages in `bytes`.
fn sent(bytes: &[u8]) -> Vec<ClientMsg> {
    let mut d = FrameDecoder::new(1 << 20);
    d.push(bytes);
    let mut out = Vec::new();
    while let Some(f) = d.next_frame().unwrap() {
        out.push(ClientMsg::decode(f).unwrap());
    }
    d.finish().unwrap();
    out
}

fn opts() -> Options {
    Options { start: Some([16.0, 16.0]), radius: 40.0, ..Options::default() }
}

/// A session through the handshake, with the welcome split across two reads.
fn welcomed() -> Session {
    let mut s = Session::new(opts());
    let hello = sent(&s.take_outbox());
    assert!(matches!(hello[..], [ClientMsg::Handshake(ClientHandshake::Hello(_))]), "{hello:?}");
    assert_eq!(s.link(), Link::Connecting);
    let w = welcome().encode_framed();
    s.on_control(&w[..7]);
    assert_eq!(s.link(), Link::Connecting);
    s.on_control(&w[7..]);
    assert_eq!(s.link(), Link::Streaming, "{:?}", s.error());
    let ready = sent(&s.take_outbox());
    match &ready[..] {
        [ClientMsg::Handshake(ClientHandshake::Ready(r))] => {
            assert_eq!(r.cells, CellMode::Expand { have_function: false });
            assert_eq!((r.viewpoint.position, r.viewpoint.radius), ([16.0, 16.0], 40.0));
        }
        other => panic!("not a ready: {other:?}"),
    }
    s
}

#[test]
fn granted_cells_are_expanded_nearest_first_within_the_budget_and_match_the_world() {
    let mut s = welcomed();
    let lane = s.open_lane();
    let other = s.open_lane();
    let vp = *s.state().viewpoint().unwrap();
    let inner = Aoi::new(&vp, &params()).inner_cells(&grid());
    assert!(inner.len() >= 4, "{inner:?}");
    let mut bytes = streaming(ServerStreaming::Function(WorldFunction { manifest: MANIFEST.into() }));
    bytes.extend(streaming(ServerStreaming::Species(SpeciesData { id: 0, graph: worm() })));
    // Split anywhere: byte by byte.
    for b in bytes.chunks(1) {
        s.on_lane(lane, b);
    }
    let mut grants = Vec::new();
    for (i, c) in inner.iter().enumerate() {
        grants.extend(streaming(ServerStreaming::Grant(CellGrant {
            cell: *c,
            grant: i as u32 + 1,
            version: 0,
            delta: None,
        })));
    }
    s.on_lane(other, &grants);
    assert_eq!(s.link(), Link::Streaming, "{:?}", s.error());
    assert_eq!((s.pending(), s.state().is_complete()), (inner.len(), false));
    // No time left: one cell all the same, the nearest (the one the viewpoint is in).
    assert_eq!(s.expand(&mut || false), 1);
    assert!(s.world_built());
    // The world built, its ground's cover is known (the page's terrain colours).
    let cover = s.cover().expect("the cover of the built world");
    assert!(cover.at(0.0, 0.0).trees + cover.at(0.0, 0.0).plants > 0.0, "the world's rules grow plants");
    let held = s.state().cells();
    assert!(held[&CellCoord::new(0, 0)].is_complete());
    assert_eq!(held.values().filter(|h| h.is_complete()).count(), 1);
    // Two more, then the rest.
    let mut calls = 0;
    assert_eq!(
        s.expand(&mut || {
            calls += 1;
            calls <= 2
        }),
        3
    );
    assert_eq!(s.expand(&mut || true), inner.len() - 4);
    assert!(s.state().is_complete() && s.pending() == 0);
    assert_eq!(s.expand(&mut || true), 0);

    let world = World::from_function("t", MANIFEST, &[SpeciesGraph::decode(&worm()).unwrap()], None).unwrap();
    let (digest, count) = held_digest(s.state());
    assert_eq!((digest, count), world_digest(&world, &inner));
    assert!(count > 0);
    let page = PageState::of(&s, [16.0, 30.0, 16.0], 0.0);
    assert_eq!(
        (page.phase, page.complete, page.records, page.cells, page.pending),
        ("streaming", true, count, inner.len(), 0)
    );
    assert_eq!(page.digest, format!("{digest:016x}"));
    let json: serde_json::Value = serde_json::from_str(&page.to_json()).unwrap();
    assert_eq!(json["error"], serde_json::Value::Null);
    assert_eq!(json["position"][1], 30.0);
    assert_eq!(json["held_cells"].as_array().unwrap().len(), inner.len());
    // Digests of sampled cells may go out, and nothing else.
    for m in sent(&s.take_outbox()) {
        assert!(matches!(m, ClientMsg::Streaming(ClientStreaming::Digest(_))), "{m:?}");
    }
}

#[test]
fn viewpoints_go_out_when_due_and_evict_what_left() {
    let mut s = welcomed();
    assert!(!s.move_to([16.5, 16.0], opts().yaw, [0.0, 0.0], Duration::from_millis(50)), "half a metre");
    assert!(s.move_to([26.0, 16.0], opts().yaw, [10.0, 0.0], Duration::from_millis(50)));
    match &sent(&s.take_outbox())[..] {
        [ClientMsg::Streaming(ClientStreaming::Viewpoint(v))] => assert_eq!((v.seq, v.position), (1, [26.0, 16.0])),
        other => panic!("{other:?}"),
    }
    s.set_radius(60.0);
    assert!(s.move_to([26.0, 16.0], opts().yaw, [0.0, 0.0], Duration::from_millis(50)), "a new radius");
    assert_eq!(s.state().viewpoint().unwrap().radius, 60.0);
    // Off the protocol's map: nothing is sent, the session goes on.
    assert!(!s.move_to([f32::NAN, 0.0], 0.0, [0.0, 0.0], Duration::from_secs(5)));
    assert_eq!(s.link(), Link::Streaming);
}

#[test]
fn faults_close_with_their_code_and_the_first_reason_stays() {
    // A streaming message on the control stream after the welcome is out of order.
    let mut s = welcomed();
    s.on_control(&streaming(ServerStreaming::Species(SpeciesData { id: 0, graph: worm() })));
    assert_eq!(s.link(), Link::Closed);
    assert_eq!(s.take_close().unwrap().code, Some(CloseCode::OutOfOrder));
    assert!(s.take_close().is_none(), "closed once");
    s.closed("the transport closed");
    assert!(s.error().unwrap().contains("Species") || s.error().unwrap().contains("species"), "{:?}", s.error());

    // A lane cut inside a frame is malformed.
    let mut s = welcomed();
    let lane = s.open_lane();
    let b = streaming(ServerStreaming::Species(SpeciesData { id: 0, graph: worm() }));
    s.on_lane(lane, &b[..b.len() - 1]);
    assert_eq!(s.link(), Link::Streaming);
    s.end_lane(lane);
    assert_eq!((s.link(), s.take_close().unwrap().code), (Link::Closed, Some(CloseCode::Malformed)));

    // Bytes that do not decode, and a species that does not hash to its entry.
    let mut s = welcomed();
    let lane = s.open_lane();
    s.on_lane(lane, &frame(&[0xff, 0xff, 0xff]));
    assert_eq!(s.link(), Link::Closed);
    assert!(s.take_close().unwrap().code.is_some());
    let mut s = welcomed();
    let lane = s.open_lane();
    s.on_lane(lane, &streaming(ServerStreaming::Species(SpeciesData { id: 0, graph: vec![1, 2, 3] })));
    assert_eq!(s.take_close().unwrap().code, Some(CloseCode::Invalid));

    // The server ending the control stream before the welcome, or the transport closing: nothing to send.
    let mut s = Session::new(opts());
    s.end_control();
    assert_eq!((s.link(), s.take_close()), (Link::Closed, None));
    let mut s = Session::new(opts());
    s.closed("refused");
    assert_eq!((s.link(), s.error()), (Link::Closed, Some("refused")));
    assert_eq!(PageState::of(&s, [0.0; 3], 0.0).phase, "closed");
}

#[test]
fn the_default_start_is_the_default_view_where_the_grid_holds_it() {
    assert_eq!(default_start(&grid()), [0.0, 0.0], "the centre of cells −4..=3");
    let big = Grid { min: CellCoord::new(-40, -40), max: CellCoord::new(39, 39), ..grid() };
    assert_eq!(default_start(&big), [40.0, -760.0]);
    let yaw = (0.0f32 - 40.0).atan2(-300.0 + 760.0);
    assert!((yaw - DEFAULT_YAW).abs() < 1e-6, "{yaw}");
}

mod far;
