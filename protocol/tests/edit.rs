//! Live edits on the wire: byte snapshots of the edit, its result, the cell delta, resume and refresh messages and
//! the versioned batch, their phases, and rejection of hostile values.

use crate::wire::{check_client, check_server};
use canopy_protocol::edit::{CellDelta, Edit, EditOp, EditOutcome, EditResult, Planted, Resume, ResumeCell};
use canopy_protocol::messages::{ClientHandshake, ClientStreaming, ServerStreaming};
use canopy_protocol::record::PackedF32;
use canopy_protocol::{
    CellBatch, CellCoord, ClientMsg, InstanceId, InstanceRecord, MessageError, Phase, ServerMsg, netlimits,
};

fn edit(op: EditOp) -> ClientMsg {
    ClientMsg::Streaming(ClientStreaming::Edit(Edit { request: 300, op }))
}

fn delta() -> CellDelta {
    CellDelta {
        cell: CellCoord::new(-3, 5),
        grant: 9,
        from_version: 4,
        to_version: 6,
        total: 131,
        adds: vec![Planted { record: InstanceRecord::new(2, 0x123, 0xabc), params: vec![(0, PackedF32(12.5))] }],
        removes: vec![7, 130],
        updates: vec![(3, vec![(1, PackedF32(2.0))])],
    }
}

#[test]
fn edits_are_pinned() {
    let id = InstanceId::new(CellCoord::new(-3, 5), 7).unwrap();
    check_client(
        &edit(EditOp::Plant { species: 2, x: 100.5, z: -20.25, params: vec![(0, 12.5)] }),
        "0101ac0200020000c9420000a2c1010000004841",
    );
    check_client(&edit(EditOp::Fell { id }), "0101ac02018780948080b0ffff7f");
    check_client(&edit(EditOp::Set { id, params: vec![(1, 2.0)] }), "0101ac02028780948080b0ffff7f010100000040");
    check_client(&ClientMsg::Streaming(ClientStreaming::Refresh(CellCoord::new(-3, 5))), "0102050a");
    check_client(&ClientMsg::Streaming(ClientStreaming::Fetch(7)), "010307");
}

#[test]
fn edit_results_are_pinned() {
    let id = InstanceId::new(CellCoord::new(-3, 5), 7).unwrap();
    let result = |outcome| ServerMsg::Streaming(ServerStreaming::EditResult(EditResult { request: 300, outcome }));
    check_server(&result(EditOutcome::Ok { id, version: 6 }), "0104ac02008780948080b0ffff7f06");
    check_server(&result(EditOutcome::Denied("read-only".into())), "0104ac020109726561642d6f6e6c79");
    check_server(&result(EditOutcome::Invalid("no".into())), "0104ac0202026e6f");
    check_server(&result(EditOutcome::Conflict), "0104ac0203");
}

#[test]
fn deltas_and_versioned_batches_are_pinned() {
    // Cell, grant, versions and total (8 bytes), one plant of 4 + 4 bytes, two removals, one update.
    check_server(
        &ServerMsg::Streaming(ServerStreaming::Delta(delta())),
        "0105050a0904068301010223c1ab01008225020782010103010102",
    );
    let batch = CellBatch::new(
        CellCoord::new(-3, 5),
        9,
        130,
        128,
        vec![InstanceRecord::new(2, 0x123, 0xabc), InstanceRecord::new(0, 4095, 0)],
        &[],
    )
    .at_version(6, [1]);
    assert!(!batch.is_felled(0) && batch.is_felled(1));
    // The version and the felled bitmap are the batch's last fields: 1 + 2 bytes here, 2 for an unedited cell.
    check_server(
        &ServerMsg::Streaming(ServerStreaming::Cells(batch)),
        "0101050a0982018001020223c1ab00ff0f0000060102".replace(' ', "").as_str(),
    );
}

#[test]
fn resume_is_legal_between_the_welcome_and_ready_only() {
    let cells = vec![
        ResumeCell { cell: CellCoord::new(-1, 0), version: 0 },
        ResumeCell { cell: CellCoord::new(2, 3), version: 17 },
    ];
    let resume = ClientMsg::Handshake(ClientHandshake::Resume(Resume { cells }));
    check_client(&resume, "0002020100000406 11".replace(' ', "").as_str());
    for phase in [Phase::Start, Phase::Hello, Phase::Welcomed, Phase::Streaming] {
        assert_eq!(resume.next_phase(phase).ok(), (phase == Phase::Welcomed).then_some(Phase::Welcomed));
    }
    let e = edit(EditOp::Fell { id: InstanceId(0) });
    assert!(e.next_phase(Phase::Welcomed).is_err());
    assert_eq!(e.next_phase(Phase::Streaming), Ok(Phase::Streaming));
}

#[test]
fn hostile_edits_deltas_and_resumes_are_refused() {
    let dec = |m: &ClientMsg| ClientMsg::decode(&m.encode());
    let nan = edit(EditOp::Plant { species: 0, x: f32::NAN, z: 0.0, params: vec![] });
    assert!(matches!(dec(&nan), Err(MessageError::Edit(_))));
    let unordered = edit(EditOp::Plant { species: 0, x: 0.0, z: 0.0, params: vec![(2, 1.0), (1, 1.0)] });
    assert!(matches!(dec(&unordered), Err(MessageError::Edit(_))));
    let inf = edit(EditOp::Set { id: InstanceId(5), params: vec![(0, f32::INFINITY)] });
    assert!(matches!(dec(&inf), Err(MessageError::Edit(_))));
    assert!(matches!(dec(&edit(EditOp::Set { id: InstanceId(5), params: vec![] })), Err(MessageError::Edit(_))));
    let many: Vec<(u16, f32)> = (0..=netlimits::MAX_EDIT_PARAMS as u16).map(|s| (s, 1.0)).collect();
    assert!(matches!(dec(&edit(EditOp::Set { id: InstanceId(5), params: many })), Err(MessageError::Count { .. })));
    let mut hello = ClientMsg::hello("a");
    if let ClientMsg::Handshake(ClientHandshake::Hello(h)) = &mut hello {
        h.token = Some(vec![1; netlimits::MAX_TOKEN_BYTES + 1]);
    }
    assert!(matches!(dec(&hello), Err(MessageError::Count { .. })));
    let repeated = ResumeCell { cell: CellCoord::new(1, 1), version: 1 };
    let resume = ClientMsg::Handshake(ClientHandshake::Resume(Resume { cells: vec![repeated, repeated] }));
    assert!(matches!(dec(&resume), Err(MessageError::Count { .. })));
    let too_many = (0..=netlimits::MAX_RESUME_PER_MESSAGE as i32)
        .map(|x| ResumeCell { cell: CellCoord::new(x, 0), version: 0 })
        .collect();
    assert!(ClientMsg::Handshake(ClientHandshake::Resume(Resume { cells: too_many })).validate().is_err());

    let sdec = |d: CellDelta| ServerMsg::decode(&ServerMsg::Streaming(ServerStreaming::Delta(d)).encode());
    assert!(sdec(delta()).is_ok());
    assert!(matches!(sdec(CellDelta { to_version: 4, ..delta() }), Err(MessageError::Edit(_))), "no version raise");
    assert!(matches!(sdec(CellDelta { removes: vec![130, 7], ..delta() }), Err(MessageError::Edit(_))));
    assert!(matches!(sdec(CellDelta { removes: vec![131], ..delta() }), Err(MessageError::Edit(_))));
    assert!(matches!(sdec(CellDelta { total: 0, ..delta() }), Err(MessageError::Edit(_))));
    let nan = vec![(3, vec![(1, PackedF32(f32::NAN))])];
    assert!(matches!(sdec(CellDelta { updates: nan, ..delta() }), Err(MessageError::Edit(_))));
    let long = EditResult { request: 1, outcome: EditOutcome::Denied("x".repeat(netlimits::MAX_EDIT_REASON + 1)) };
    assert!(ServerMsg::decode(&ServerMsg::Streaming(ServerStreaming::EditResult(long)).encode()).is_err());
    let bad_bits = CellBatch {
        felled: vec![0, 0],
        ..CellBatch::new(CellCoord::new(0, 0), 1, 2, 0, vec![InstanceRecord::new(0, 0, 0); 2], &[])
    };
    assert!(ServerMsg::decode(&ServerMsg::Streaming(ServerStreaming::Cells(bad_bits)).encode()).is_err());
}
