//! The sans-IO session core on virtual time, without sockets: handshake and phase legality, area of interest with
//! look-ahead and hysteresis, nearest-first and in-view-first order, species once, pacing and the window.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_protocol::aoi::{AoiParams, Grid, Viewpoint};
use canopy_protocol::messages::ServerMsgKind;
use canopy_protocol::messages::{ClientHandshake, Hello, ServerHandshake, ServerStreaming};
use canopy_protocol::{CellCoord, ClientMsg, CloseCode, InstanceId, PROTOCOL_VERSION, Phase, ServerMsg, SpeciesGraph};
use canopy_session::{PlacedInstance, StoreBuilder, WorldStore};
use canopy_session::{Session, SessionConfig, SessionError, StreamId, Transmit};

const CELL: f32 = 32.0;

/// A 16 × 16 grid of 32 m cells around the origin; cell (x, z) holds `(x + z).rem_euclid(5) + 1` instances of
/// species `(x * 7 + z).rem_euclid(3)`; every third instance overrides parameter 0.
fn store() -> Arc<dyn WorldStore> {
    let species: Vec<SpeciesGraph> =
        ["worm", "conifer", "bush"].iter().map(|n| canopy_worlds::library::find(n).unwrap().load().unwrap()).collect();
    let grid = Grid { origin: [0.0, 0.0], cell_size: CELL, min: CellCoord::new(-8, -8), max: CellCoord::new(7, 7) };
    let mut b = StoreBuilder::new("test", 7, grid, terrain(), &species).unwrap();
    for z in -8i32..8 {
        for x in -8i32..8 {
            let n = (x + z).rem_euclid(5) as usize + 1;
            let o = grid.cell_origin(CellCoord::new(x, z));
            let instances: Vec<PlacedInstance> = (0..n)
                .map(|i| PlacedInstance {
                    species: (x * 7 + z).rem_euclid(3) as u16,
                    x: o[0] + 1.0 + i as f32 * 5.0,
                    z: o[1] + 2.0 + i as f32 * 3.0,
                    params: if i % 3 == 0 { vec![(0, 3.0 + i as f32)] } else { vec![] },
                })
                .collect();
            b.add_cell(CellCoord::new(x, z), &instances).unwrap();
        }
    }
    b.finish().shared()
}

fn terrain() -> canopy_protocol::messages::TerrainDesc {
    canopy_protocol::messages::TerrainDesc::flat([-256.0, -256.0], 512.0)
}

fn config() -> SessionConfig {
    SessionConfig {
        aoi: AoiParams { max_radius: 200.0, hysteresis: 24.0, lookahead_s: 2.0, max_lookahead: 64.0 },
        batch_records: 4,
        ..SessionConfig::default()
    }
}

fn decode(t: &Transmit) -> ServerMsg {
    let frame = t.frame();
    assert_eq!(u32::from_le_bytes(frame[..4].try_into().unwrap()) as usize, frame.len() - 4);
    ServerMsg::decode(&frame[4..]).unwrap()
}

/// A session driven to the streaming phase at `vp`, with its welcome drained.
fn streaming(store: &Arc<dyn WorldStore>, cfg: SessionConfig, vp: Viewpoint, have: Vec<u8>, t0: Instant) -> Session {
    let mut s = Session::new(Arc::clone(store), cfg, t0);
    s.handle(t0, ClientMsg::hello("test")).unwrap();
    let w = s.poll_transmit(t0).unwrap();
    assert_eq!(w.stream, StreamId::Control);
    assert!(matches!(decode(&w), ServerMsg::Handshake(ServerHandshake::Welcome(_))));
    s.on_flushed(w.len());
    assert_eq!(s.phase(), Phase::Welcomed);
    s.handle(t0, ClientMsg::ready(have, vp)).unwrap();
    assert_eq!(s.phase(), Phase::Streaming);
    s
}

/// Everything the session sends until it is idle (the window reopened as bytes go).
fn drain(s: &mut Session, now: Instant) -> Vec<(StreamId, ServerMsg)> {
    let mut out = vec![];
    while let Some(t) = s.poll_transmit(now) {
        s.on_flushed(t.len());
        out.push((t.stream, decode(&t)));
    }
    out
}

fn cells_of(msgs: &[(StreamId, ServerMsg)]) -> Vec<CellCoord> {
    let mut cells = vec![];
    for (_, m) in msgs {
        if let ServerMsg::Streaming(ServerStreaming::Cells(b)) = m
            && cells.last() != Some(&b.cell)
        {
            cells.push(b.cell);
        }
    }
    cells
}

#[test]
fn streams_the_area_of_interest_nearest_first_with_each_species_once() {
    let store = store();
    let t0 = Instant::now();
    let vp = Viewpoint::at(0, [10.0, 10.0], 100.0);
    let mut s = streaming(&store, config(), vp, vec![], t0);
    let msgs = drain(&mut s, t0);
    assert!(s.is_complete());
    let grid = *store.grid();
    let aoi = canopy_protocol::aoi::Aoi::new(&vp, &config().aoi);
    let inner: HashSet<CellCoord> = aoi.inner_cells(&grid).into_iter().collect();
    // Every cell of the area of interest, once, in full; nothing else.
    let cells = cells_of(&msgs);
    assert_eq!(cells.len(), inner.len());
    assert_eq!(cells.iter().copied().collect::<HashSet<_>>(), inner);
    let mut got: HashMap<CellCoord, Vec<InstanceId>> = HashMap::new();
    let mut species_sent = vec![];
    for (lane, m) in &msgs {
        assert!(matches!(lane, StreamId::Lane(_)));
        match m {
            ServerMsg::Streaming(ServerStreaming::Cells(b)) => {
                let view = store.cell(b.cell, None).ready().unwrap();
                assert_eq!(usize::from(b.total), view.records.len());
                for (i, r) in b.records.iter().enumerate() {
                    assert!(species_sent.contains(&r.species), "species {} sent after its first instance", r.species);
                    assert_eq!(*r, view.records[usize::from(b.start) + i]);
                    got.entry(b.cell).or_default().push(b.id(i));
                }
                for o in &b.overrides() {
                    let cell_index = usize::from(b.start) + usize::from(o.record);
                    assert!(
                        view.overrides
                            .iter()
                            .any(|v| usize::from(v.record) == cell_index && v.slot == o.slot && v.value == o.value)
                    );
                }
            }
            ServerMsg::Streaming(ServerStreaming::Species(sp)) => {
                assert!(!species_sent.contains(&sp.id), "species {} sent twice", sp.id);
                assert_eq!(sp.graph, store.species_graph(sp.id).unwrap());
                species_sent.push(sp.id);
            }
            m => panic!("unexpected {m:?}"),
        }
    }
    for (c, ids) in &got {
        let v = store.cell(*c, None).ready().unwrap();
        // Every record of the cell once, named (cell, index in the cell).
        let expected: Vec<InstanceId> = (0..v.records.len()).map(|i| InstanceId::new(*c, i as u16).unwrap()).collect();
        assert_eq!(*ids, expected);
    }
    // Nearest first: distances from the viewpoint never decrease by more than a cell's diagonal among in-view
    // cells (a cell out of view counts double).
    let d: Vec<f32> = cells.iter().map(|c| grid.distance2(*c, vp.position).sqrt()).collect();
    assert_eq!(d[0], 0.0, "the cell under the viewpoint comes first");
    let in_view = |c: &CellCoord| {
        let d = grid.distance2(*c, vp.position).sqrt();
        let o = grid.cell_origin(*c);
        let (dx, dz) = (o[0] + CELL * 0.5 - vp.position[0], o[1] + CELL * 0.5 - vp.position[1]);
        let len = (dx * dx + dz * dz).sqrt();
        d <= CELL || dz >= (60f32).to_radians().cos() * len
    };
    let in_view_first: Vec<f32> =
        cells.iter().filter(|c| in_view(c)).map(|c| grid.distance2(*c, vp.position).sqrt()).collect();
    assert!(in_view_first.windows(2).all(|w| w[0] <= w[1]), "{in_view_first:?}");
    assert_eq!(s.stats().messages[ServerMsgKind::Species], 3);
}

#[test]
fn cells_in_view_come_before_cells_behind_at_the_same_distance() {
    let store = store();
    let t0 = Instant::now();
    // Looking along +z (yaw 0) from the middle of cell (0, 0).
    let vp = Viewpoint { seq: 0, position: [16.0, 16.0], yaw: 0.0, velocity: [0.0, 0.0], radius: 120.0 };
    let mut s = streaming(&store, config(), vp, vec![0, 1, 2], t0);
    let cells = cells_of(&drain(&mut s, t0));
    let pos = |c: CellCoord| cells.iter().position(|&x| x == c).unwrap();
    // (0, 3) ahead and (0, -3) behind are equally far.
    assert!(pos(CellCoord::new(0, 3)) < pos(CellCoord::new(0, -3)));
    assert!(pos(CellCoord::new(1, 2)) < pos(CellCoord::new(1, -2)));
    // Turned around, the order flips.
    let vp = Viewpoint { yaw: std::f32::consts::PI, ..vp };
    let mut s = streaming(&store, config(), vp, vec![0, 1, 2], t0);
    let cells = cells_of(&drain(&mut s, t0));
    let pos = |c: CellCoord| cells.iter().position(|&x| x == c).unwrap();
    assert!(pos(CellCoord::new(0, 3)) > pos(CellCoord::new(0, -3)));
}

#[test]
fn species_the_client_holds_are_not_sent() {
    let store = store();
    let t0 = Instant::now();
    let mut s = streaming(&store, config(), Viewpoint::at(0, [0.0, 0.0], 150.0), vec![0, 2], t0);
    let msgs = drain(&mut s, t0);
    let sent: Vec<u8> = msgs
        .iter()
        .filter_map(|(_, m)| match m {
            ServerMsg::Streaming(ServerStreaming::Species(sp)) => Some(sp.id),
            _ => None,
        })
        .collect();
    assert_eq!(sent, vec![1]);
}

#[test]
fn look_ahead_requests_cells_along_the_velocity() {
    let store = store();
    let t0 = Instant::now();
    let at_rest = Viewpoint::at(0, [0.0, 0.0], 64.0);
    let moving = Viewpoint { velocity: [20.0, 0.0], ..at_rest };
    let mut a = streaming(&store, config(), at_rest, vec![0, 1, 2], t0);
    let mut b = streaming(&store, config(), moving, vec![0, 1, 2], t0);
    let rest: HashSet<CellCoord> = cells_of(&drain(&mut a, t0)).into_iter().collect();
    let ahead: HashSet<CellCoord> = cells_of(&drain(&mut b, t0)).into_iter().collect();
    assert!(rest.is_subset(&ahead));
    // 20 m/s × 2 s = 40 m ahead along +x: cells past x = 64 m are needed only when moving.
    assert!(ahead.contains(&CellCoord::new(3, 0)) && !rest.contains(&CellCoord::new(3, 0)));
    assert!(!ahead.contains(&CellCoord::new(-4, 0)));
}

/// Oscillate across the border of the area of interest; count grants and releases.
fn churn(hysteresis: f32) -> (u64, u64) {
    let store = store();
    let t0 = Instant::now();
    let mut cfg = config();
    cfg.aoi.hysteresis = hysteresis;
    let mut s = streaming(&store, cfg, Viewpoint::at(0, [0.0, 0.0], 100.0), vec![0, 1, 2], t0);
    drain(&mut s, t0);
    let mut grants = 0;
    let mut releases = 0;
    for seq in 1..=40u32 {
        if seq == 2 {
            // Count from the second step on: the first step's new cells are a real change.
            grants = s.stats().grants;
            releases = 0;
        }
        // Walking back and forth by 8 m along x, so cells come and go at the radius on both sides.
        let x = if seq % 2 == 0 { 0.0 } else { 8.0 };
        s.handle(t0, ClientMsg::viewpoint(Viewpoint::at(seq, [x, 0.0], 100.0))).unwrap();
        releases += drain(&mut s, t0)
            .iter()
            .filter(|(_, m)| matches!(m, ServerMsg::Streaming(ServerStreaming::Release(_))))
            .count() as u64;
    }
    (s.stats().grants - grants, releases)
}

#[test]
fn hysteresis_stops_churn_at_the_border() {
    assert_eq!(churn(24.0), (0, 0), "with hysteresis nothing is granted or released after the first step");
    let (grants, releases) = churn(0.0);
    assert!(
        grants >= 19 && releases >= 19,
        "without hysteresis the border churns: {grants} grants, {releases} releases"
    );
}

#[test]
fn cells_left_behind_are_released_and_regranted_with_newer_grants() {
    let store = store();
    let t0 = Instant::now();
    let mut s = streaming(&store, config(), Viewpoint::at(0, [-200.0, -200.0], 40.0), vec![0, 1, 2], t0);
    let first: HashMap<CellCoord, u32> = drain(&mut s, t0)
        .iter()
        .filter_map(|(_, m)| match m {
            ServerMsg::Streaming(ServerStreaming::Cells(b)) => Some((b.cell, b.grant)),
            _ => None,
        })
        .collect();
    s.handle(t0, ClientMsg::viewpoint(Viewpoint::at(1, [200.0, 200.0], 40.0))).unwrap();
    let msgs = drain(&mut s, t0);
    // Every old cell is released with its grant, on the lane its batches used, before any new batch.
    let released: HashMap<CellCoord, u32> = msgs
        .iter()
        .filter_map(|(_, m)| match m {
            ServerMsg::Streaming(ServerStreaming::Release(r)) => Some((r.cell, r.grant)),
            _ => None,
        })
        .collect();
    assert_eq!(released, first);
    assert_eq!(s.held_cells().count(), cells_of(&msgs).len());
    s.handle(t0, ClientMsg::viewpoint(Viewpoint::at(2, [-200.0, -200.0], 40.0))).unwrap();
    let back = drain(&mut s, t0);
    let max_old = first.values().max().unwrap();
    for (_, m) in &back {
        if let ServerMsg::Streaming(ServerStreaming::Cells(b)) = m {
            assert!(b.grant > *max_old);
        }
    }
    assert_eq!(cells_of(&back).into_iter().collect::<HashSet<_>>(), first.keys().copied().collect());
}

#[test]
fn a_bandwidth_cap_paces_and_keeps_the_nearest_first() {
    let store = store();
    let t0 = Instant::now();
    let mut cfg = config();
    cfg.bandwidth = Some(1_000);
    cfg.burst = 500;
    let vp = Viewpoint::at(0, [0.0, 0.0], 200.0);
    let mut s = streaming(&store, cfg, vp, vec![0, 1, 2], t0);
    let mut now = t0;
    let mut sent_by_second = vec![0usize; 40];
    let mut order = vec![];
    while !s.is_complete() && now < t0 + Duration::from_secs(39) {
        match s.poll_transmit(now) {
            Some(t) => {
                s.on_flushed(t.len());
                sent_by_second[now.duration_since(t0).as_secs() as usize] += t.len();
                let cell = cells_of(&[(t.stream, decode(&t))]);
                if order.last() != cell.first() {
                    order.extend(cell);
                }
            }
            None => now = s.poll_timeout().expect("paced, not idle"),
        }
    }
    assert!(s.is_complete(), "all sent within 39 s");
    let full: Vec<usize> = sent_by_second[1..sent_by_second.iter().rposition(|&b| b > 0).unwrap()].to_vec();
    assert!(full.len() >= 3);
    for b in &full {
        assert!((850..=1_150).contains(b), "bytes per second {full:?}");
    }
    // The same order as without the cap: pacing delays, it does not reorder.
    let mut free = streaming(&store, config(), vp, vec![0, 1, 2], t0);
    assert_eq!(order, cells_of(&drain(&mut free, t0)));
}

#[test]
fn the_window_holds_back_until_bytes_are_flushed() {
    let store = store();
    let t0 = Instant::now();
    let mut cfg = config();
    cfg.window = 300;
    let mut s = streaming(&store, cfg, Viewpoint::at(0, [0.0, 0.0], 200.0), vec![0, 1, 2], t0);
    let mut held = 0;
    while let Some(t) = s.poll_transmit(t0) {
        held += t.len();
    }
    assert!((300..300 + 200).contains(&held), "{held}");
    assert!(!s.is_complete());
    s.on_flushed(held);
    assert!(s.poll_transmit(t0).is_some());
}

fn error_of(msgs: Vec<ClientMsg>) -> SessionError {
    let store = store();
    let t0 = Instant::now();
    let mut s = Session::new(store, config(), t0);
    for m in msgs {
        if let Err(e) = s.handle(t0, m) {
            return e;
        }
        while s.poll_transmit(t0).is_some() {}
    }
    panic!("no error");
}

#[test]
fn messages_out_of_order_or_invalid_end_the_session_with_a_code() {
    let vp = Viewpoint::at(0, [0.0, 0.0], 50.0);
    let e = error_of(vec![ClientMsg::viewpoint(vp)]);
    assert_eq!(e.close_code(), CloseCode::OutOfOrder, "{e}");
    let e = error_of(vec![ClientMsg::ready(vec![], vp)]);
    assert_eq!(e.close_code(), CloseCode::OutOfOrder, "{e}");
    let e = error_of(vec![ClientMsg::hello("a"), ClientMsg::hello("b")]);
    assert_eq!(e.close_code(), CloseCode::OutOfOrder, "{e}");
    let e = error_of(vec![ClientMsg::hello("a"), ClientMsg::ready(vec![], vp), ClientMsg::viewpoint(vp)]);
    assert!(matches!(e, SessionError::Stale { seq: 0, last: 0 }), "{e}");
    let e = error_of(vec![ClientMsg::hello("a"), ClientMsg::ready(vec![9], vp)]);
    assert_eq!(e, SessionError::UnknownSpecies(9));
    let old = ClientMsg::Handshake(ClientHandshake::Hello(Hello { version: 0, client: "old".into(), token: None }));
    let e = error_of(vec![old]);
    assert_eq!(e.close_code(), CloseCode::Version);
    assert_eq!(e.to_string(), format!("client speaks protocol version 0, server speaks {PROTOCOL_VERSION}"));
    let bad = Viewpoint::at(0, [f32::NAN, 0.0], 50.0);
    let e = error_of(vec![ClientMsg::hello("a"), ClientMsg::ready(vec![], bad)]);
    assert_eq!(e.close_code(), CloseCode::Invalid, "{e}");
    // Bytes that do not decode.
    let mut s = Session::new(store(), config(), Instant::now());
    let e = s.handle_frame(Instant::now(), &[0xff, 0xff, 0xff]).unwrap_err();
    assert_eq!(e.close_code(), CloseCode::Malformed);
    let e = s.handle_frame(Instant::now(), &vec![0u8; 5000]).unwrap_err();
    assert_eq!(e.close_code(), CloseCode::TooLarge);
}

#[test]
fn a_client_that_never_finishes_its_handshake_times_out() {
    let t0 = Instant::now();
    let mut s = Session::new(store(), config(), t0);
    s.handle(t0, ClientMsg::hello("slow")).unwrap();
    let deadline = s.poll_timeout().unwrap();
    assert_eq!(deadline, t0 + config().handshake_timeout);
    assert!(s.handle_timeout(deadline - Duration::from_millis(1)).is_ok());
    assert_eq!(s.handle_timeout(deadline).unwrap_err().close_code(), CloseCode::Timeout);
}

#[test]
fn server_memory_per_session_is_bounded_by_the_area_of_interest() {
    // Whatever viewpoints a client sends, the session holds at most the cells within radius + hysteresis.
    let store = store();
    let t0 = Instant::now();
    let cfg = config();
    let mut s = streaming(&store, cfg.clone(), Viewpoint::at(0, [0.0, 0.0], 1e9), vec![0, 1, 2], t0);
    let grid = *store.grid();
    let mut x: u64 = 99;
    for seq in 1..200u32 {
        x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let p = [((x >> 33) % 600) as f32 - 300.0, ((x >> 13) % 600) as f32 - 300.0];
        let vp = Viewpoint { seq, position: p, yaw: 0.0, velocity: [(x % 50) as f32, 0.0], radius: 1e9 };
        // Ten viewpoints a second: within the session's viewpoint rate.
        let now = t0 + Duration::from_millis(100 * u64::from(seq));
        s.handle(now, ClientMsg::viewpoint(vp)).unwrap();
        // Send a little, not all: partially sent cells must be bounded too.
        for _ in 0..(x % 20) {
            if let Some(t) = s.poll_transmit(now) {
                s.on_flushed(t.len());
            }
        }
        let aoi = canopy_protocol::aoi::Aoi::new(&vp, &cfg.aoi);
        assert!(s.held_cells().all(|(c, _)| aoi.is_kept(&grid, c)));
    }
}

/// A geometry source for the payload-mode tests: blobs whose sizes say what they are.
struct FakeGeometry;

impl canopy_session::GeometrySource for FakeGeometry {
    fn instance_mesh(&self, id: InstanceId) -> Arc<Vec<u8>> {
        // Large enough to need several chunks for every third instance of a cell.
        let index = usize::from(id.index());
        let n =
            if index.is_multiple_of(3) { 2 * canopy_protocol::netlimits::MAX_GEOMETRY_CHUNK + 5 } else { 100 + index };
        Arc::new(vec![id.0 as u8; n])
    }
    fn species_mesh(&self, species: u8) -> Arc<Vec<u8>> {
        Arc::new(vec![species; 1000])
    }
    fn transforms(&self, _cell: CellCoord, records: std::ops::Range<u16>) -> Vec<u8> {
        vec![7; 32 * records.len()]
    }
}

fn payload_config(mode: canopy_session::PayloadMode) -> SessionConfig {
    SessionConfig { payload: canopy_session::Payload::new(mode, Arc::new(FakeGeometry)), ..config() }
}

#[test]
fn explicit_payloads_go_through_the_same_area_of_interest() {
    use canopy_protocol::messages::GeometryKind;
    use canopy_session::PayloadMode;
    let store = store();
    let t0 = Instant::now();
    let vp = Viewpoint::at(0, [10.0, 10.0], 100.0);
    let mut procedural = streaming(&store, config(), vp, vec![], t0);
    let reference = drain(&mut procedural, t0);
    let records = procedural.stats().records;
    for mode in [PayloadMode::UniqueMesh, PayloadMode::Instanced] {
        let mut s = streaming(&store, payload_config(mode), vp, vec![], t0);
        let msgs = drain(&mut s, t0);
        assert!(s.is_complete());
        assert_eq!(s.stats().records, records, "{mode:?}: the same instances");
        assert_eq!(
            cells_of(&msgs).into_iter().collect::<HashSet<_>>(),
            cells_of(&reference).into_iter().collect::<HashSet<_>>(),
            "{mode:?}: the same cells"
        );
        // Per blob: the chunks arrive in order and add up to its size, before the batch that needs it.
        let mut blobs: HashMap<(u8, u64), (u32, u32)> = HashMap::new();
        let mut species_meshes = HashSet::new();
        for (_, m) in &msgs {
            match m {
                ServerMsg::Streaming(ServerStreaming::Species(_)) => panic!("{mode:?} sends no species programs"),
                ServerMsg::Streaming(ServerStreaming::Geometry(g)) => {
                    let e = blobs.entry((g.kind as u8, g.id)).or_insert((0, g.total));
                    assert_eq!(e.0, g.offset, "chunks in order");
                    e.0 += g.bytes.len() as u32;
                    if g.kind == GeometryKind::SpeciesMesh {
                        assert!(species_meshes.insert(g.id) || g.offset > 0, "each species mesh once");
                    }
                }
                ServerMsg::Streaming(ServerStreaming::Cells(b)) => {
                    // Geometry names the batch's first instance: its cell and `start`.
                    let (first, n) = (b.id(0), b.records.len() as u32);
                    assert_eq!((first.cell(), first.index()), (b.cell, b.start));
                    match mode {
                        PayloadMode::UniqueMesh => {
                            assert_eq!(n, 1, "one instance per unit");
                            let (got, total) = blobs[&(GeometryKind::InstanceMesh as u8, first.0)];
                            assert_eq!(got, total, "the mesh is through before its record");
                        }
                        _ => {
                            let (got, total) = blobs[&(GeometryKind::Transforms as u8, first.0)];
                            assert_eq!((got, total), (32 * n, 32 * n));
                            for r in &b.records {
                                assert!(species_meshes.contains(&u64::from(r.species)), "species mesh first");
                            }
                        }
                    }
                }
                _ => {}
            }
        }
        // Accounting: the session's byte counters are the transmitted bytes.
        let geometry: u64 = msgs
            .iter()
            .filter(|(_, m)| matches!(m, ServerMsg::Streaming(ServerStreaming::Geometry(_))))
            .map(|(_, m)| m.encode().len() as u64 + 4)
            .sum();
        assert_eq!(s.stats().bytes[ServerMsgKind::Geometry], geometry);
        assert_eq!(s.stats().bytes[ServerMsgKind::Species], 0);
    }
}

#[test]
fn a_release_takes_back_staged_geometry() {
    use canopy_session::PayloadMode;
    let store = store();
    let t0 = Instant::now();
    let mut s =
        streaming(&store, payload_config(PayloadMode::UniqueMesh), Viewpoint::at(0, [10.0, 10.0], 100.0), vec![], t0);
    // Start one unit, then jump far away before it is through: its cell is released, the rest never goes.
    let first = s.poll_transmit(t0).unwrap();
    s.on_flushed(first.len());
    let far = Viewpoint::at(1, [-200.0, -200.0], 30.0);
    s.handle(t0, ClientMsg::viewpoint(far)).unwrap();
    let msgs = drain(&mut s, t0);
    let released: HashSet<CellCoord> = msgs
        .iter()
        .filter_map(|(_, m)| match m {
            ServerMsg::Streaming(ServerStreaming::Release(r)) => Some(r.cell),
            _ => None,
        })
        .collect();
    assert!(!released.is_empty());
    for (_, m) in &msgs {
        if let ServerMsg::Streaming(ServerStreaming::Cells(b)) = m {
            assert!(!released.contains(&b.cell), "no batch of a released cell after its release");
        }
    }
    assert!(s.is_complete());
}

#[test]
fn a_long_non_ascii_world_name_is_cut_to_the_byte_limit_and_the_welcome_decodes() {
    let grid = Grid { origin: [0.0, 0.0], cell_size: CELL, min: CellCoord::new(0, 0), max: CellCoord::new(1, 1) };
    let name = "Wald der großen Föhren ".repeat(10);
    let store = StoreBuilder::new(&name, 1, grid, terrain(), &[]).unwrap().finish().shared();
    let cut = &store.world().name;
    assert!(cut.len() <= canopy_protocol::netlimits::MAX_WORLD_NAME && cut.len() > 120, "{} bytes", cut.len());
    assert!(name.starts_with(cut.as_str()));
    let t0 = Instant::now();
    let mut s = Session::new(Arc::clone(&store), config(), t0);
    s.handle(t0, ClientMsg::hello("test")).unwrap();
    match decode(&s.poll_transmit(t0).unwrap()) {
        ServerMsg::Handshake(ServerHandshake::Welcome(w)) => assert_eq!(&w.world, store.world()),
        m => panic!("expected the welcome, got {m:?}"),
    }
}

#[test]
fn a_world_a_client_would_refuse_is_refused_by_the_store() {
    let grid = Grid { origin: [0.0, 0.0], cell_size: CELL, min: CellCoord::new(0, 0), max: CellCoord::new(1, 1) };
    let bad = canopy_protocol::messages::TerrainDesc { corners: vec![0.0; 3], ..terrain() };
    let e = StoreBuilder::new("test", 1, grid, bad, &[]).unwrap_err();
    assert!(matches!(e, canopy_session::StoreError::World(_)), "{e:?}");
    let bad_grid = Grid { cell_size: -1.0, ..grid };
    let e = StoreBuilder::new("test", 1, bad_grid, terrain(), &[]).unwrap_err();
    assert!(matches!(e, canopy_session::StoreError::Grid(_)), "{e:?}");
    // A grid reaching past the cells instance ids can name.
    let far = CellCoord::new(InstanceId::CELL_MAX - 1, 0);
    let beyond = Grid { min: far, max: CellCoord::new(far.x + 2, 1), ..grid };
    let e = StoreBuilder::new("test", 1, beyond, terrain(), &[]).unwrap_err();
    assert!(matches!(e, canopy_session::StoreError::Grid(_)), "{e:?}");
    let edge = Grid { min: far, max: CellCoord::new(far.x + 1, 1), ..grid };
    assert!(StoreBuilder::new("test", 1, edge, terrain(), &[]).is_ok());
    // An instance that names a species the table lacks is reported by its (cell, index).
    let mut b = StoreBuilder::new("test", 1, grid, terrain(), &[]).unwrap();
    let p = PlacedInstance { species: 0, x: 1.0, z: 1.0, params: vec![] };
    let e = b.add_cell(CellCoord::new(1, 0), &[p]).unwrap_err();
    let id = InstanceId::new(CellCoord::new(1, 0), 0).unwrap();
    assert_eq!(e, canopy_session::StoreError::UnknownSpecies { id, species: 0 });
}

#[test]
fn a_viewpoint_flood_ends_the_session() {
    let store = store();
    let t0 = Instant::now();
    let mut s = streaming(&store, config(), Viewpoint::at(0, [0.0, 0.0], 100.0), vec![0, 1, 2], t0);
    // Ten a second for a minute is fine (an honest client sends at most that).
    let mut seq = 0;
    for i in 0..600u64 {
        seq += 1;
        let now = t0 + Duration::from_millis(100 * i);
        let vp = Viewpoint::at(seq, [(i % 40) as f32, 0.0], 100.0);
        s.handle(now, ClientMsg::viewpoint(vp)).unwrap();
        drain(&mut s, now);
    }
    // Thousands within one second are not: the burst (twice the rate) goes, then the session ends.
    let now = t0 + Duration::from_secs(61);
    let mut accepted = 0;
    let err = loop {
        seq += 1;
        match s.handle(now, ClientMsg::viewpoint(Viewpoint::at(seq, [0.0, 0.0], 100.0))) {
            Ok(()) => accepted += 1,
            Err(e) => break e,
        }
        assert!(accepted <= 200, "never stopped");
    };
    let (rate, burst) = SessionConfig::default().viewpoint_rate;
    assert!(accepted <= burst as usize + 1, "{accepted}");
    assert!(matches!(err, SessionError::ViewpointFlood(r) if r == rate), "{err}");
    assert_eq!(err.close_code(), CloseCode::Invalid);
}

#[test]
fn a_session_never_flushed_stays_within_its_window_through_teleports() {
    let store = store();
    let t0 = Instant::now();
    let cfg = SessionConfig { window: 4 * 1024, ..config() };
    let mut s = streaming(&store, cfg.clone(), Viewpoint::at(0, [0.0, 0.0], 200.0), vec![], t0);
    let mut most = 0;
    let mut largest = 0;
    // A client that never acknowledges anything, teleporting corner to corner for ten virtual minutes.
    for i in 0..6_000u64 {
        let now = t0 + Duration::from_millis(100 * i);
        if i % 10 == 0 {
            let corner = [[-200.0, -200.0], [200.0, 200.0], [-200.0, 200.0], [200.0, -200.0]][(i / 10 % 4) as usize];
            s.handle(now, ClientMsg::viewpoint(Viewpoint::at(1 + (i / 10) as u32, corner, 200.0))).unwrap();
        }
        while let Some(t) = s.poll_transmit(now) {
            if t.class != ServerMsgKind::Release {
                largest = largest.max(t.len());
            }
        }
        most = most.max(s.unflushed());
    }
    // Paced messages stop at the window (one may cross it); releases are small and bounded by the cells held.
    let releases = s.stats().bytes[ServerMsgKind::Release] as usize;
    assert!(most <= cfg.window + largest + releases, "{most}");
    assert!(s.unflushed() <= cfg.window + largest + releases);
    assert!(s.stats().bytes[ServerMsgKind::Cells] as usize <= cfg.window + largest, "nothing paced past the window");
}

#[test]
fn the_shared_send_budget_pauses_sessions_until_bytes_are_flushed() {
    use canopy_session::SendBudget;
    let store = store();
    let t0 = Instant::now();
    let budget = SendBudget::new(6 * 1024);
    let cfg = SessionConfig { window: 64 * 1024, send_budget: Some(Arc::clone(&budget)), ..config() };
    let mut a = streaming(&store, cfg.clone(), Viewpoint::at(0, [0.0, 0.0], 200.0), vec![], t0);
    let mut b = streaming(&store, cfg, Viewpoint::at(0, [50.0, 50.0], 200.0), vec![], t0);
    // Neither flushes: together they stop at the shared budget, far below their windows.
    let mut a_sent = vec![];
    while let Some(t) = a.poll_transmit(t0) {
        a_sent.push(t.len());
    }
    while b.poll_transmit(t0).is_some() {}
    assert!(budget.spent());
    assert!(budget.used() < 6 * 1024 + 2 * 4096, "{}", budget.used());
    assert_eq!(budget.used(), a.unflushed() + b.unflushed());
    assert!(b.poll_timeout().is_some(), "a paused session asks to be polled again");
    // A flushes what it had: B goes on.
    a.on_flushed(a_sent.iter().sum());
    assert!(!budget.spent());
    assert!(b.poll_transmit(t0 + Duration::from_millis(5)).is_some());
    // A session that ends gives its bytes back.
    drop(b);
    assert_eq!(budget.used(), a.unflushed());
}

/// A small world as a function (its manifest offered to clients that expand cells), in a store of its cells.
fn function_store() -> (Arc<dyn WorldStore>, canopy_worlds::world::World) {
    let text = "world tiny\nseed 7\nbounds -128 -128 128 128\ncell 32\nspecies worm worm\nspecies conifer conifer\n\
                scatter conifer {\n  spacing 9\n}\n";
    let src = canopy_worlds::diag::SourceFile::new("tiny.world", text);
    let world = canopy_worlds::world::World::parse(&src, None).unwrap();
    (canopy_session::GridStore::from_world(&world).unwrap().shared(), world)
}

fn expanding(store: &Arc<dyn WorldStore>, vp: Viewpoint, t0: Instant) -> Session {
    use canopy_protocol::messages::{CellMode, Ready};
    let mut s = Session::new(Arc::clone(store), config(), t0);
    s.handle(t0, ClientMsg::hello("test")).unwrap();
    let w = s.poll_transmit(t0).unwrap();
    let ServerMsg::Handshake(ServerHandshake::Welcome(w)) = decode(&w) else { panic!("a welcome") };
    assert!(w.world.function.is_some(), "a world function is offered");
    let ready = Ready { have: vec![], viewpoint: vp, cells: CellMode::Expand { have_function: false } };
    s.handle(t0, ClientMsg::Handshake(ClientHandshake::Ready(ready))).unwrap();
    s
}

#[test]
fn a_client_that_expands_gets_the_function_every_species_and_grants_and_its_digests_are_checked() {
    use canopy_protocol::messages::{CellDigest, ClientStreaming, cell_digest};
    let (store, _world) = function_store();
    let t0 = Instant::now();
    let vp = Viewpoint::at(1, [0.0, 0.0], 60.0);
    let mut s = expanding(&store, vp, t0);
    let sent = drain(&mut s, t0);
    let kinds: Vec<ServerMsgKind> = sent.iter().map(|(_, m)| m.kind()).collect();
    assert_eq!(kinds[0], ServerMsgKind::Function);
    assert_eq!(kinds.iter().filter(|k| **k == ServerMsgKind::Species).count(), 2, "every species, once");
    assert!(!kinds.contains(&ServerMsgKind::Cells), "no records");
    let granted: Vec<CellCoord> = sent
        .iter()
        .filter_map(|(_, m)| match m {
            ServerMsg::Streaming(ServerStreaming::Grant(g)) => Some(g.cell),
            _ => None,
        })
        .collect();
    assert!(granted.len() >= 9 && s.is_complete(), "{granted:?}");
    assert_eq!(s.stats().expand_grants as usize, granted.len());
    // The right digest is checked and passes; a wrong one is caught and the cell comes as records.
    let data = |c: CellCoord| store.cell(c, None).ready().unwrap();
    let (good, bad) = (granted[0], granted[1]);
    let digest = |c: CellCoord| {
        let d = data(c);
        cell_digest(&d.records, &d.overrides, d.felled.iter().copied())
    };
    let report = |c: CellCoord, digest: u64| {
        ClientMsg::Streaming(ClientStreaming::Digest(CellDigest { cell: c, version: 0, digest }))
    };
    s.handle(t0, report(good, digest(good))).unwrap();
    s.handle(t0, report(bad, digest(bad) ^ 1)).unwrap();
    let again = drain(&mut s, t0);
    assert_eq!((s.stats().digests_checked, s.stats().digest_mismatches), (2, 1));
    assert_eq!(cells_of(&again), vec![bad], "the cell whose digest differed comes again as records");
    assert!(s.is_complete());
    // A client that asks for a cell's records gets them.
    s.handle(t0, ClientMsg::Streaming(ClientStreaming::Records(good))).unwrap();
    assert_eq!(cells_of(&drain(&mut s, t0)), vec![good]);
    // A digest of a cell outside the world ends the session.
    let outside = report(CellCoord::new(1000, 0), 0);
    assert_eq!(s.handle(t0, outside).unwrap_err().close_code(), CloseCode::Invalid);
}

/// A store of edited cells over another: each edited cell's delta from version 0, changed by the test.
struct Edited {
    base: Arc<dyn WorldStore>,
    edits: std::sync::Mutex<std::collections::BTreeMap<CellCoord, canopy_protocol::edit::CellDelta>>,
}

impl WorldStore for Edited {
    fn head(&self) -> &canopy_session::StoreHead {
        self.base.head()
    }
    fn cell(&self, c: CellCoord, waker: Option<&Arc<dyn canopy_session::CellWaker>>) -> canopy_session::CellState {
        self.base.cell(c, waker)
    }
    fn version(
        &self,
        c: CellCoord,
        waker: Option<&Arc<dyn canopy_session::CellWaker>>,
    ) -> canopy_session::VersionState {
        match self.edits.lock().unwrap().contains_key(&c) {
            true => canopy_session::VersionState::Edited,
            false => self.base.version(c, waker),
        }
    }
    fn changes(
        &self,
        c: CellCoord,
        from: u32,
        _: Option<&Arc<dyn canopy_session::CellWaker>>,
    ) -> canopy_session::Changes {
        match self.edits.lock().unwrap().get(&c) {
            Some(d) if from == 0 => canopy_session::Changes::Delta(d.clone()),
            Some(_) => canopy_session::Changes::Whole,
            None => canopy_session::Changes::Current { total: 0 },
        }
    }
    fn edited_cells(&self, lo: CellCoord, hi: CellCoord, max: usize) -> Vec<(CellCoord, u32)> {
        let edits = self.edits.lock().unwrap();
        let index = edits.iter().map(|(c, d)| (*c, d.to_version)).collect();
        canopy_session::cells_in(&index, lo, hi, max)
    }
}

fn felled_in(cell: CellCoord, version: u32) -> canopy_protocol::edit::CellDelta {
    let removes = (0..version as u16).collect();
    canopy_protocol::edit::CellDelta {
        cell,
        grant: 0,
        from_version: 0,
        to_version: version,
        total: 40,
        adds: vec![],
        removes,
        updates: vec![],
    }
}

fn far_cells(msgs: &[(StreamId, ServerMsg)]) -> Vec<(CellCoord, u32)> {
    msgs.iter()
        .filter_map(|(_, m)| match m {
            ServerMsg::Streaming(ServerStreaming::FarCell(f)) => Some((f.cell, f.version())),
            _ => None,
        })
        .collect()
}

#[test]
fn a_client_that_expands_is_told_of_edited_cells_within_its_far_view_and_of_their_changes() {
    use canopy_protocol::messages::ClientStreaming;
    use canopy_protocol::summary::FarView;
    let (base, _world) = function_store();
    let (near, far, beyond) = (CellCoord::new(-4, -4), CellCoord::new(-4, 1), CellCoord::new(3, -4));
    let edits = [(near, felled_in(near, 1)), (far, felled_in(far, 2)), (beyond, felled_in(beyond, 1))];
    let edited = Arc::new(Edited { base, edits: std::sync::Mutex::new(edits.into_iter().collect()) });
    let store: Arc<dyn WorldStore> = edited.clone();
    let t0 = Instant::now();
    // In the world's south-west corner (cells of 32 m from -128): `near` is in the area of interest, `far` 160 m
    // away along z, `beyond` 224 m along x.
    let vp = Viewpoint::at(1, [-112.0, -112.0], 40.0);
    let mut s = expanding(&store, vp, t0);
    drain(&mut s, t0);
    let view = |range: f32| FarView { error_px: 16.0, height_px: 720, fov_y: 1.0, range, altitude: 2.0 };
    s.handle(t0, ClientMsg::Streaming(ClientStreaming::FarView(view(215.0)))).unwrap();
    let sent = drain(&mut s, t0);
    // The edited cell within range and beyond the area of interest, with its edits; the one in the area of
    // interest comes as its grant, the one out of range not at all; no summaries (the client computes them).
    assert_eq!(far_cells(&sent), vec![(far, 2)]);
    assert!(sent.iter().all(|(_, m)| m.kind() != ServerMsgKind::Summaries));
    assert_eq!(s.far_cells(), vec![(far, 2)]);
    // Nothing more until something changes.
    assert!(far_cells(&drain(&mut s, t0)).is_empty());
    // Another edit of the far cell: told again at once (no look needed), and once a version (announced again,
    // nothing goes).
    edited.edits.lock().unwrap().insert(far, felled_in(far, 3));
    s.on_cell_changed(far);
    assert_eq!(far_cells(&drain(&mut s, t0)), vec![(far, 3)]);
    s.on_cell_changed(far);
    assert!(far_cells(&drain(&mut s, t0)).is_empty());
    // A cell not told of yet changes: looked for once the last look is LOOK_INTERVAL (250 ms) old.
    let other = CellCoord::new(-3, 1);
    edited.edits.lock().unwrap().insert(other, felled_in(other, 1));
    s.on_cell_changed(other);
    assert!(far_cells(&drain(&mut s, t0)).is_empty(), "a look at most every 250 ms");
    assert_eq!(s.poll_timeout(), Some(t0 + Duration::from_millis(250)));
    let t1 = t0 + Duration::from_millis(250);
    assert_eq!(far_cells(&drain(&mut s, t1)), vec![(other, 1)]);
    // A longer range reaches the cell beyond too; those told of are not sent again.
    s.handle(t1, ClientMsg::Streaming(ClientStreaming::FarView(view(300.0)))).unwrap();
    assert_eq!(far_cells(&drain(&mut s, t1 + Duration::from_millis(250))), vec![(beyond, 1)]);
    // A client that takes records asks for summaries as before and is told of no far cell.
    let mut r = streaming(&store, config(), vp, vec![], t0);
    r.handle(t0, ClientMsg::Streaming(ClientStreaming::FarView(view(300.0)))).unwrap();
    assert!(far_cells(&drain(&mut r, t0)).is_empty() && r.far_cells().is_empty());
}
