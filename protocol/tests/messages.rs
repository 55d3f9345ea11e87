//! The streaming protocol's wire: byte snapshots of every message variant, round trips, phase legality, framing,
//! and rejection of malformed, oversized and hostile bytes (a stable-toolchain stand-in for the fuzz targets).

use crate::wire::{check_client, check_server, hex};
use canopy_protocol::aoi::{AoiParams, Grid, Viewpoint};
use canopy_protocol::edit::CellDelta;
use canopy_protocol::frame::{FrameDecoder, FrameError, frame};
use canopy_protocol::messages::{
    CellDigest, CellGrant, ClientHandshake, ClientStreaming, FarCell, FractalDesc, Hello, Release, ServerHandshake,
    ServerMsgKind, ServerStreaming, SpeciesData, SpeciesEntry, TerrainDesc, Welcome, WorldFunction, WorldInfo,
    cell_digest,
};
use canopy_protocol::record::{BatchError, PackedF32, ParamOverride, dequantize, quantize};
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{
    CellBatch, CellCoord, ClientMsg, InstanceId, InstanceRecord, MessageError, POSITION_STEPS, PROTOCOL_VERSION, Phase,
    ServerMsg, SpeciesHash, netlimits,
};

fn viewpoint() -> Viewpoint {
    Viewpoint { seq: 7, position: [100.5, -20.25], yaw: 1.5, velocity: [3.0, -4.0], radius: 160.0 }
}

fn batch() -> CellBatch {
    CellBatch::new(
        CellCoord::new(-3, 5),
        9,
        130,
        128,
        vec![InstanceRecord::new(2, 0x123, 0xabc), InstanceRecord::new(0, 4095, 0)],
        &[ParamOverride { record: 1, slot: 3, value: 12.5 }],
    )
}

fn welcome() -> Welcome {
    Welcome {
        version: PROTOCOL_VERSION,
        world: WorldInfo {
            name: "forest".into(),
            seed: 0x5eed_f0e5,
            grid: Grid {
                origin: [0.0, 0.0],
                cell_size: 64.0,
                min: CellCoord::new(-16, -16),
                max: CellCoord::new(15, 15),
            },
            position_steps: POSITION_STEPS,
            instances: 111_556,
            terrain: TerrainDesc {
                graph: Some(vec![1, 2, 3]),
                seed: 7,
                origin: [-1024.0, -1024.0],
                tile_size: 512.0,
                tiles: [1, 1],
                depth: 7,
                corners: vec![1.0, 2.0, 3.0, 4.0],
                params: vec![(4, 2.2)],
                fractal: None,
            },
            function: Some(SpeciesHash::of(b"forest.world")),
        },
        species: vec![SpeciesEntry { hash: SpeciesHash([0xab; 32]), size: 1234 }],
        aoi: AoiParams::default(),
    }
}

#[test]
fn hello_is_pinned() {
    check_client(&ClientMsg::hello("bot-1"), "00000705626f742d3100");
}

#[test]
fn ready_is_pinned() {
    check_client(
        &ClientMsg::ready(vec![0, 3], viewpoint()),
        "0001020003070000c9420000a2c10000c03f00004040000080c00000204300",
    );
}

#[test]
fn viewpoint_is_pinned() {
    check_client(&ClientMsg::viewpoint(viewpoint()), "0100070000c9420000a2c10000c03f00004040000080c000002043");
}

#[test]
fn welcome_is_pinned() {
    check_server(
        &ServerMsg::Handshake(ServerHandshake::Welcome(welcome())),
        "00000706666f72657374e5e1b7f7050000000000000000000080421f1f1e1e8020c4e706010301020307000080c4000080c40000004401\
         0107040000803f0000004000004040000080400104cdcc0c4000010610c39861ffddeaf018d1930586a354855feaa7de91b94b69e710\
         4ad5e7dc9701ababababababababababababababababababababababababababababababababd2090000004400000042000000400000\
         0043",
    );
}

/// A welcome whose ground is a fractal: its numbers, no height grid.
fn fractal_welcome() -> Welcome {
    let mut w = welcome();
    w.world.terrain = TerrainDesc {
        fractal: Some(FractalDesc {
            seed: 0x4849_4748,
            origin: [-51200.0, -51200.0],
            tile: 12800.0,
            depth: 11,
            dimension: 2.25,
            relief: 260.0,
            dims: [2, 2],
            heights: vec![300.0, 600.0, 200.0, 450.0],
        }),
        ..TerrainDesc::flat([-51200.0, -51200.0], 102400.0)
    };
    w
}

#[test]
fn fractal_welcome_is_pinned() {
    check_server(
        &ServerMsg::Handshake(ServerHandshake::Welcome(fractal_welcome())),
        "00000706666f72657374e5e1b7f7050000000000000000000080421f1f1e1e8020c4e7060000000048c7000048c70000c8470101000400\
         0000000000000000000000000000000001c88ea5c204000000000000e9c0000000000000e9c0000000000000c9400b00001040000082\
         430202040000964300001644000048430000e143010610c39861ffddeaf018d1930586a354855feaa7de91b94b69e7104ad5e7dc9701\
         ababababababababababababababababababababababababababababababababd20900000044000000420000004000000043",
    );
}

#[test]
fn fractal_numbers_out_of_range_are_refused() {
    let sdec = |w: Welcome| ServerMsg::decode(&ServerMsg::Handshake(ServerHandshake::Welcome(w)).encode());
    let change = |f: &dyn Fn(&mut FractalDesc)| {
        let mut w = fractal_welcome();
        f(w.world.terrain.fractal.as_mut().expect("fractal"));
        sdec(w)
    };
    assert!(change(&|_| {}).is_ok());
    assert!(change(&|f| f.dims = [0, 0]).is_err());
    assert!(
        change(&|f| {
            f.dims = [0, 0];
            f.heights.clear();
        })
        .is_ok()
    );
    let refused: [&dyn Fn(&mut FractalDesc); 14] = [
        &|f| f.depth = netlimits::MAX_FRACTAL_DEPTH + 1,
        &|f| f.depth = 40,
        &|f| f.tile = 1.0,
        &|f| f.tile = f64::NAN,
        &|f| f.tile = f64::INFINITY,
        &|f| f.dimension = 3.0,
        &|f| f.dimension = 1.99,
        &|f| f.dimension = f32::NAN,
        &|f| f.relief = -1.0,
        &|f| f.relief = f32::INFINITY,
        &|f| f.origin[1] = f64::NAN,
        &|f| f.heights[2] = f32::NAN,
        &|f| f.heights.pop().map_or((), drop),
        &|f| {
            f.dims = [256, 257];
            f.heights = vec![0.0; 256 * 257];
        },
    ];
    for (k, f) in refused.iter().enumerate() {
        assert!(matches!(change(*f), Err(MessageError::World(_)) | Err(MessageError::TooLarge { .. })), "case {k}");
    }
    // The largest control grid is accepted.
    assert!(
        change(&|f| {
            f.dims = [256, 256];
            f.heights = vec![1.0; netlimits::MAX_CONTROL_HEIGHTS];
        })
        .is_ok()
    );
}

#[test]
fn species_is_pinned() {
    check_server(
        &ServerMsg::Streaming(ServerStreaming::Species(SpeciesData { id: 4, graph: vec![9, 8, 7] })),
        "010004 03090807".replace(' ', "").as_str(),
    );
}

#[test]
fn cells_is_pinned() {
    // An 8-byte header (cell, grant, total, start, record count: no instance id, the identity is the cell and the
    // index), two records of 4 bytes each, one parameter column of 7 bytes: the column count, the slot, the bitmap
    // with its length, the value count and 12.5 in 2 bytes; then the cell version (0) and an empty felled bitmap.
    check_server(
        &ServerMsg::Streaming(ServerStreaming::Cells(batch())),
        "0101050a0982018001020223c1ab00ff0f00010301020182250000",
    );
}

#[test]
fn release_is_pinned() {
    check_server(
        &ServerMsg::Streaming(ServerStreaming::Release(Release { cell: CellCoord::new(-3, 5), grant: 9 })),
        "0102050a09",
    );
}

#[test]
fn parameter_columns_round_trip_and_short_values_are_short() {
    let overrides = [
        ParamOverride { record: 0, slot: 1, value: 18.0 },
        ParamOverride { record: 0, slot: 4, value: 0.1 },
        ParamOverride { record: 9, slot: 1, value: -2.5 },
        ParamOverride { record: 12, slot: 1, value: f32::MAX },
    ];
    let records = vec![InstanceRecord::new(0, 0, 0); 13];
    let b = CellBatch::new(CellCoord::new(0, 0), 1, 13, 0, records, &overrides);
    assert_eq!(b.params.len(), 2);
    assert_eq!(b.params[0].present, vec![0b0000_0001, 0b0001_0010]);
    assert_eq!(b.overrides(), overrides);
    assert_eq!(b.validate(), Ok(()));
    let size = |v: f32| postcard::to_allocvec(&PackedF32(v)).unwrap().len();
    assert_eq!((size(12.5), size(18.0), size(0.25), size(1.0)), (2, 2, 2, 2));
    assert_eq!(size(0.1), 5);
    for v in [0.0, -0.0, 1.5, f32::MIN_POSITIVE, -7.25e9] {
        let bytes = postcard::to_allocvec(&PackedF32(v)).unwrap();
        assert_eq!(postcard::from_bytes::<PackedF32>(&bytes).unwrap().0.to_bits(), v.to_bits());
    }
}

#[test]
fn records_are_four_bytes_and_positions_round_trip() {
    let r = InstanceRecord::new(200, 4095, 17);
    assert_eq!((r.qx(), r.qz(), r.species), (4095, 17, 200));
    assert_eq!(postcard::to_allocvec(&r).unwrap().len(), 4);
    for cell_size in [1.0f32, 64.0, 4096.0] {
        for q in [0u16, 1, 2047, 4095] {
            let origin = -1024.0;
            let v = dequantize(q, origin, cell_size);
            assert_eq!(quantize(v.into(), origin.into(), cell_size), q, "cell {cell_size} step {q}");
        }
        assert_eq!(quantize(f64::NAN, 0.0, cell_size), 0);
        assert_eq!(quantize(1e9, 0.0, cell_size), 4095);
    }
}

#[test]
fn instance_ids_pack_cell_and_index_at_the_extremes() {
    let far = 1 << 20;
    let cells = [
        CellCoord::new(0, 0),
        CellCoord::new(-3, 5),
        CellCoord::new(far, -far),
        CellCoord::new(-far, far),
        CellCoord::new(far, far),
        CellCoord::new(-far, -far),
        CellCoord::new(InstanceId::CELL_MIN, InstanceId::CELL_MAX),
        CellCoord::new(InstanceId::CELL_MAX, InstanceId::CELL_MIN),
    ];
    let mut ids = vec![];
    for cell in cells {
        for index in [0u16, 1, 65534, 65535] {
            let id = InstanceId::new(cell, index).expect("a nameable cell");
            assert_eq!((id.cell(), id.index()), (cell, index), "{id:?}");
            ids.push(((cell, index), id));
        }
    }
    // The numeric order of ids is the order of (cell, index), and distinct pairs get distinct ids.
    ids.sort_by_key(|&(key, _)| key);
    assert!(ids.windows(2).all(|w| w[0].1 < w[1].1));
    // The layout is pinned: x + 2^23 in bits 63..40, z + 2^23 in bits 39..16, the index in bits 15..0.
    assert_eq!(InstanceId::new(CellCoord::new(0, 0), 0), Some(InstanceId(0x8000_0080_0000_0000)));
    assert_eq!(InstanceId::new(CellCoord::new(-1, 1), 7), Some(InstanceId(0x7fff_ff80_0001_0007)));
    assert_eq!(InstanceId::new(CellCoord::new(InstanceId::CELL_MIN, InstanceId::CELL_MIN), 0), Some(InstanceId(0)));
    assert_eq!(
        InstanceId::new(CellCoord::new(InstanceId::CELL_MAX, InstanceId::CELL_MAX), u16::MAX),
        Some(InstanceId(u64::MAX))
    );
    // Cells outside 24 bits per axis have no ids; every u64 is an id of some (cell, index).
    for cell in [
        CellCoord::new(InstanceId::CELL_MAX + 1, 0),
        CellCoord::new(0, InstanceId::CELL_MIN - 1),
        CellCoord::new(i32::MIN, i32::MAX),
    ] {
        assert_eq!(InstanceId::new(cell, 0), None, "{cell:?}");
    }
    let mut rng = XorShift64::new(7);
    for _ in 0..1000 {
        let id = InstanceId(rng.next());
        assert_eq!(InstanceId::new(id.cell(), id.index()), Some(id));
    }
    // A batch names its records (cell, start + i).
    let b = batch();
    assert_eq!(b.id(1), InstanceId::new(CellCoord::new(-3, 5), 129).unwrap());
}

#[test]
fn frames_are_length_prefixed_and_bounded_before_buffering() {
    let f = frame(&[1, 2, 3]);
    assert_eq!(hex(&f), "03000000010203");
    // Split anywhere: the decoder reassembles.
    let two: Vec<u8> = [frame(b"hello"), frame(b"world!")].concat();
    for cut in 0..two.len() {
        let mut d = FrameDecoder::new(16);
        let mut got = vec![];
        for part in [&two[..cut], &two[cut..]] {
            d.push(part);
            while let Some(f) = d.next_frame().unwrap() {
                got.push(f.to_vec());
            }
        }
        assert_eq!(got, vec![b"hello".to_vec(), b"world!".to_vec()]);
        assert_eq!(d.finish(), Ok(()));
    }
    // An oversized length is refused as soon as the prefix arrives.
    let mut d = FrameDecoder::new(16);
    d.push(&(1u32 << 31).to_le_bytes());
    assert_eq!(d.next_frame(), Err(FrameError::TooLarge { len: 1 << 31, max: 16 }));
    let mut d = FrameDecoder::new(16);
    d.push(&[0, 0, 0, 0]);
    assert_eq!(d.next_frame(), Err(FrameError::Empty));
    let mut d = FrameDecoder::new(16);
    d.push(&[5, 0, 0, 0, 1]);
    assert_eq!(d.next_frame(), Ok(None));
    assert_eq!(d.finish(), Err(FrameError::Truncated(5)));
}

#[test]
fn each_message_is_legal_only_in_its_phase() {
    let hello = ClientMsg::hello("a");
    let ready = ClientMsg::ready(vec![], viewpoint());
    let vp = ClientMsg::viewpoint(viewpoint());
    let welcome = ServerMsg::Handshake(ServerHandshake::Welcome(welcome()));
    let cells = ServerMsg::Streaming(ServerStreaming::Cells(batch()));
    assert_eq!(hello.next_phase(Phase::Start), Ok(Phase::Hello));
    assert_eq!(welcome.next_phase(Phase::Hello), Ok(Phase::Welcomed));
    assert_eq!(ready.next_phase(Phase::Welcomed), Ok(Phase::Streaming));
    assert_eq!(vp.next_phase(Phase::Streaming), Ok(Phase::Streaming));
    assert_eq!(cells.next_phase(Phase::Streaming), Ok(Phase::Streaming));
    for phase in [Phase::Start, Phase::Hello, Phase::Welcomed, Phase::Streaming] {
        assert_eq!(hello.next_phase(phase).is_ok(), phase == Phase::Start);
        assert_eq!(ready.next_phase(phase).is_ok(), phase == Phase::Welcomed);
        assert_eq!(vp.next_phase(phase).is_ok(), phase == Phase::Streaming);
        assert_eq!(welcome.next_phase(phase).is_ok(), phase == Phase::Hello);
        assert_eq!(cells.next_phase(phase).is_ok(), phase == Phase::Streaming);
    }
    let e = vp.next_phase(Phase::Welcomed).unwrap_err();
    assert_eq!(e.to_string(), "viewpoint is not legal in phase Welcomed");
}

#[test]
fn invalid_values_are_rejected_after_decoding() {
    let dec = |m: &ClientMsg| ClientMsg::decode(&m.encode());
    let mut v = viewpoint();
    v.position[0] = f32::INFINITY;
    assert!(matches!(dec(&ClientMsg::viewpoint(v)), Err(MessageError::Viewpoint(_))));
    v = viewpoint();
    v.radius = -1.0;
    assert!(matches!(dec(&ClientMsg::viewpoint(v)), Err(MessageError::Viewpoint(_))));
    assert!(matches!(dec(&ClientMsg::ready(vec![3, 1], viewpoint())), Err(MessageError::Count { .. })));
    assert!(matches!(dec(&ClientMsg::ready(vec![1, 1], viewpoint())), Err(MessageError::Count { .. })));
    let long = ClientMsg::Handshake(ClientHandshake::Hello(Hello { version: 1, client: "x".repeat(65), token: None }));
    assert!(matches!(dec(&long), Err(MessageError::Count { what: "client name", .. })));

    let sdec = |m: ServerMsg| ServerMsg::decode(&m.encode());
    let cells = |b: CellBatch| ServerMsg::Streaming(ServerStreaming::Cells(b));
    let mut b = batch();
    b.start = 129;
    assert_eq!(sdec(cells(b)), Err(MessageError::Batch(BatchError::Range { start: 129, end: 131, total: 130 })));
    let column = |e| Err(MessageError::Batch(BatchError::Column(e)));
    let mut b = batch();
    b.params[0].present = vec![0b100];
    assert_eq!(sdec(cells(b)), column(0), "a bit past the records");
    let mut b = batch();
    b.params[0].present = vec![0b11];
    assert_eq!(sdec(cells(b)), column(0), "two bits, one value");
    let mut b = batch();
    b.params.push(b.params[0].clone());
    assert_eq!(sdec(cells(b)), column(1), "a slot twice");
    let mut b = batch();
    b.params[0].values[0] = PackedF32(f32::NAN);
    assert_eq!(sdec(cells(b)), column(0));
    let mut b = batch();
    b.params[0].present = vec![];
    b.params[0].values.clear();
    assert_eq!(sdec(cells(b)), column(0), "a bitmap of the wrong length");
    let mut b = batch();
    b.records.clear();
    b.params.clear();
    assert_eq!(sdec(cells(b)), Err(MessageError::Batch(BatchError::Empty(130))));
    let mut b = batch();
    b.records = vec![InstanceRecord::new(0, 0, 0); netlimits::MAX_BATCH_RECORDS + 1];
    b.total = u16::MAX;
    b.start = 0;
    assert!(matches!(sdec(cells(b)), Err(MessageError::Batch(BatchError::TooManyRecords(_)))));
    for cell in [CellCoord::new(InstanceId::CELL_MAX + 1, 0), CellCoord::new(0, InstanceId::CELL_MIN - 1)] {
        let mut b = batch();
        b.cell = cell;
        assert_eq!(sdec(cells(b)), Err(MessageError::Batch(BatchError::Cell(cell))), "ids cannot name the cell");
    }

    let welcome = |w: Welcome| ServerMsg::Handshake(ServerHandshake::Welcome(w));
    let mut w = welcome_fixture();
    w.world.grid.cell_size = 0.0;
    assert!(matches!(sdec(welcome(w)), Err(MessageError::Grid(_))));
    let mut w = welcome_fixture();
    w.world.grid.max = CellCoord::new(i32::MAX, 0);
    assert!(matches!(sdec(welcome(w)), Err(MessageError::Grid(_))));
    let mut w = welcome_fixture();
    w.world.position_steps = 1024;
    assert!(matches!(sdec(welcome(w)), Err(MessageError::World(_))));
    let mut w = welcome_fixture();
    w.world.terrain.corners.pop();
    assert!(matches!(sdec(welcome(w)), Err(MessageError::World(_))));
    let mut w = welcome_fixture();
    w.world.terrain.depth = 40;
    assert!(matches!(sdec(welcome(w)), Err(MessageError::World(_))));
    let mut w = welcome_fixture();
    w.aoi.max_radius = f32::NAN;
    assert!(matches!(sdec(welcome(w)), Err(MessageError::Aoi(_))));
    let mut w = welcome_fixture();
    w.species = vec![w.species[0]; netlimits::MAX_SPECIES + 1];
    assert!(matches!(sdec(welcome(w)), Err(MessageError::Count { what: "species table", .. })));
}

fn welcome_fixture() -> Welcome {
    welcome()
}

#[test]
fn oversized_truncated_and_trailing_bytes_are_rejected() {
    let big = vec![0u8; netlimits::MAX_CLIENT_FRAME + 1];
    assert!(matches!(ClientMsg::decode(&big), Err(MessageError::TooLarge { .. })));
    let big = vec![0u8; netlimits::MAX_SERVER_FRAME + 1];
    assert!(matches!(ServerMsg::decode(&big), Err(MessageError::TooLarge { .. })));
    for msg in [ClientMsg::hello("bot"), ClientMsg::ready(vec![1, 2], viewpoint()), ClientMsg::viewpoint(viewpoint())] {
        let bytes = msg.encode();
        for cut in 0..bytes.len() {
            assert!(ClientMsg::decode(&bytes[..cut]).is_err(), "{} cut at {cut}", msg.name());
        }
        let mut extra = bytes.clone();
        extra.push(0);
        assert_eq!(ClientMsg::decode(&extra), Err(MessageError::Trailing(1)));
    }
    for msg in server_messages() {
        let bytes = msg.encode();
        for cut in 0..bytes.len() {
            assert!(ServerMsg::decode(&bytes[..cut]).is_err(), "{} cut at {cut}", msg.name());
        }
    }
    // A length prefix claiming 2^32 entries must fail without allocating them.
    let hostile = [0x01, 0x00, 0xff, 0xff, 0xff, 0xff, 0x0f, 0x01];
    assert!(ServerMsg::decode(&hostile).is_err());
}

fn server_messages() -> Vec<ServerMsg> {
    vec![
        ServerMsg::Handshake(ServerHandshake::Welcome(welcome())),
        ServerMsg::Handshake(ServerHandshake::Welcome(fractal_welcome())),
        ServerMsg::Streaming(ServerStreaming::Species(SpeciesData { id: 1, graph: vec![1, 2, 3, 4] })),
        ServerMsg::Streaming(ServerStreaming::Cells(batch())),
        ServerMsg::Streaming(ServerStreaming::Release(Release { cell: CellCoord::new(1, 2), grant: 3 })),
        grant(2, Some(felled(0, 2))),
        ServerMsg::Streaming(ServerStreaming::Function(WorldFunction { manifest: "seed 1".into() })),
    ]
}

fn xorshift(seed: u64) -> impl FnMut() -> u64 {
    let mut x = XorShift64::new(seed);
    move || x.next()
}

#[test]
fn random_bytes_never_panic() {
    // Deterministic mutations of valid encodings and random junk: decoders return, never panic, and whatever they
    // accept re-encodes to bytes that decode to the same message.
    let mut next = xorshift(0x2545_f491_4f6c_dd1d);
    let client: Vec<Vec<u8>> =
        [ClientMsg::hello("bot"), ClientMsg::ready(vec![0, 1], viewpoint()), ClientMsg::viewpoint(viewpoint())]
            .iter()
            .map(ClientMsg::encode)
            .collect();
    let server: Vec<Vec<u8>> = server_messages().iter().map(ServerMsg::encode).collect();
    for round in 0..20_000 {
        for (bases, is_client) in [(&client, true), (&server, false)] {
            let mut b = bases[round % bases.len()].clone();
            for _ in 0..1 + next() % 4 {
                let i = (next() as usize) % b.len();
                b[i] = next() as u8;
            }
            if next().is_multiple_of(8) {
                b.truncate((next() as usize) % (b.len() + 1));
            }
            if is_client {
                if let Ok(m) = ClientMsg::decode(&b) {
                    assert_eq!(ClientMsg::decode(&m.encode()), Ok(m));
                }
            } else if let Ok(m) = ServerMsg::decode(&b) {
                assert_eq!(ServerMsg::decode(&m.encode()), Ok(m));
            }
        }
        let len = (next() % 64) as usize;
        let junk: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        let _ = ClientMsg::decode(&junk);
        let _ = ServerMsg::decode(&junk);
        let mut d = FrameDecoder::new(64);
        d.push(&junk);
        while let Ok(Some(_)) = d.next_frame() {}
    }
}

#[test]
fn species_hashes_are_sha256_of_the_encoding() {
    let h = SpeciesHash::of(b"abc");
    assert_eq!(h.hex(), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    assert_eq!(SpeciesHash::from_hex(&h.hex()), Some(h));
    assert_eq!(SpeciesHash::from_hex("zz"), None);
}

#[test]
fn geometry_is_pinned_and_bounded() {
    use canopy_protocol::messages::{GeometryChunk, GeometryKind};
    let chunk = |kind, offset: u32, total: u32, bytes: Vec<u8>| {
        ServerMsg::Streaming(ServerStreaming::Geometry(GeometryChunk { kind, id: 300, offset, total, bytes }))
    };
    // The last variant of the streaming messages: the earlier variants' encodings are unchanged.
    check_server(&chunk(GeometryKind::Transforms, 0, 3, vec![1, 2, 3]), "010302ac02000303010203");
    assert_eq!(chunk(GeometryKind::InstanceMesh, 0, 1, vec![9]).name(), "geometry");
    // A chunk larger than its limit, one that runs past its blob, or a blob larger than its limit are refused.
    let big = netlimits::MAX_GEOMETRY_CHUNK;
    for bad in [
        chunk(GeometryKind::InstanceMesh, 0, big as u32 + 1, vec![0; big + 1]),
        chunk(GeometryKind::SpeciesMesh, 10, 12, vec![0; 3]),
        chunk(GeometryKind::InstanceMesh, 0, netlimits::MAX_GEOMETRY_BYTES as u32 + 1, vec![0; 4]),
        chunk(GeometryKind::InstanceMesh, u32::MAX, 4, vec![0; 4]),
        // Species ids fit the species table (instance ids are any u64).
        chunk(GeometryKind::SpeciesMesh, 0, 4, vec![0; 4]),
    ] {
        assert!(matches!(ServerMsg::decode(&bad.encode()), Err(MessageError::Count { .. })), "{bad:?}");
    }
    assert!(ServerMsg::decode(&chunk(GeometryKind::InstanceMesh, 4, 8, vec![0; 4]).encode()).is_ok());
    let id = InstanceId::new(CellCoord::new(-(1 << 20), 1 << 20), 65535).unwrap();
    for kind in [GeometryKind::InstanceMesh, GeometryKind::Transforms] {
        let g = GeometryChunk { kind, id: id.0, offset: 0, total: 1, bytes: vec![1] };
        assert_eq!(g.instance(), Some(id));
        let msg = ServerMsg::Streaming(ServerStreaming::Geometry(g));
        assert_eq!(ServerMsg::decode(&msg.encode()), Ok(msg));
    }
    let g = GeometryChunk { kind: GeometryKind::SpeciesMesh, id: 255, offset: 0, total: 1, bytes: vec![1] };
    assert_eq!(g.instance(), None);
    assert!(ServerMsg::decode(&ServerMsg::Streaming(ServerStreaming::Geometry(g)).encode()).is_ok());
}

fn grant(version: u32, delta: Option<CellDelta>) -> ServerMsg {
    ServerMsg::Streaming(ServerStreaming::Grant(CellGrant { cell: CellCoord::new(-3, 5), grant: 9, version, delta }))
}

fn felled(from_version: u32, to_version: u32) -> CellDelta {
    CellDelta {
        cell: CellCoord::new(-3, 5),
        grant: 9,
        from_version,
        to_version,
        total: 12,
        adds: vec![],
        removes: vec![4],
        updates: vec![],
    }
}

#[test]
fn grants_functions_digests_and_record_asks_are_pinned_and_checked() {
    // An unedited cell's grant: the cell, the grant, version 0, no delta: five bytes after the kind.
    check_server(&grant(0, None), "0107050a090000");
    check_server(&grant(2, Some(felled(0, 2))), "0107050a090201050a0900020c00010400");
    let function = ServerMsg::Streaming(ServerStreaming::Function(WorldFunction { manifest: "seed 1".into() }));
    check_server(&function, "010806736565642031");
    let ask = ClientMsg::Streaming(ClientStreaming::Records(CellCoord::new(1, -1)));
    check_client(&ask, "01050201");
    let digest = CellDigest { cell: CellCoord::new(1, -1), version: 3, digest: 0x0123_4567_89ab_cdef };
    check_client(&ClientMsg::Streaming(ClientStreaming::Digest(digest)), "0106020103ef9bafcdf8acd19101");
    // A grant must say what its delta does: from version 0 to the grant's version, of its own cell.
    for bad in [grant(2, None), grant(2, Some(felled(1, 2))), grant(3, Some(felled(0, 2)))] {
        assert!(matches!(ServerMsg::decode(&bad.encode()), Err(MessageError::Edit(_))), "{bad:?}");
    }
    let huge = WorldFunction { manifest: "#".repeat(netlimits::MAX_FUNCTION_BYTES + 1) };
    let huge = ServerMsg::Streaming(ServerStreaming::Function(huge));
    assert!(matches!(ServerMsg::decode(&huge.encode()), Err(MessageError::Count { .. })));
    // The function's hash is the SHA-256 of its manifest: what a welcome names.
    assert_eq!(WorldFunction { manifest: "seed 1".into() }.hash(), SpeciesHash::of(b"seed 1"));
}

#[test]
fn far_cells_are_pinned_and_must_carry_their_edits_from_version_0() {
    let far = |delta: CellDelta| ServerMsg::Streaming(ServerStreaming::FarCell(FarCell { cell: delta.cell, delta }));
    let edits = CellDelta { grant: 0, ..felled(0, 2) };
    assert_eq!(far(edits.clone()).kind(), ServerMsgKind::FarCell);
    check_server(&far(edits.clone()), "0109050a050a0000020c00010400");
    // Not from version 0, numbered as a grant, of another cell, or an inconsistent delta: refused.
    let other = CellDelta { cell: CellCoord::new(1, 1), ..edits.clone() };
    let wrong = ServerMsg::Streaming(ServerStreaming::FarCell(FarCell { cell: CellCoord::new(-3, 5), delta: other }));
    for bad in [
        far(CellDelta { grant: 0, ..felled(1, 2) }),
        far(felled(0, 2)),
        wrong,
        far(CellDelta { removes: vec![12], ..edits }),
    ] {
        assert!(matches!(ServerMsg::decode(&bad.encode()), Err(MessageError::Edit(_))), "{bad:?}");
    }
}

#[test]
fn cell_digests_see_every_record_override_and_felled_index() {
    let records = [InstanceRecord::new(1, 10, 20), InstanceRecord::new(2, 30, 40)];
    let overrides = [ParamOverride { record: 1, slot: 2, value: 3.5 }];
    let d = cell_digest(&records, &overrides, [0]);
    assert_eq!(d, cell_digest(&records, &overrides, [0]));
    assert_ne!(d, cell_digest(&records, &overrides, []));
    assert_ne!(d, cell_digest(&records[..1], &overrides, [0]));
    assert_ne!(d, cell_digest(&[records[1], records[0]], &overrides, [0]));
    assert_ne!(d, cell_digest(&records, &[ParamOverride { value: 3.25, ..overrides[0] }], [0]));
    assert_ne!(d, cell_digest(&records, &[], [0]));
}
