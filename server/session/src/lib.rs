//! The sans-IO core of the Canopy world server (seed 001 §4): what one client is sent, in which order and when.
//!
//! Like quinn-proto, nothing here touches a socket, reads the clock or needs an async runtime: a [`Session`] is fed
//! `now` and the client's messages and says what to send ([`Transmit`]) and when to wake it; tests drive it on
//! virtual time. It reads the world through the [`WorldStore`] trait (a materialised [`GridStore`], or the server's
//! cell cache and live edits behind the same trait), never waiting for a cell: a store that has not expanded a cell
//! yet says so and wakes the session ([`CellWaker`]) when it has.
//!
//! Contract: anything a client sends is untrusted. A message that does not decode, is too large or comes out of
//! order ends that session with a [`SessionError`] (a [`canopy_protocol::CloseCode`] and a reason).

mod batch;
pub mod counters;
mod editors;
mod far;
mod pacing;
mod payload;
mod session;
mod store;
mod summaries;
mod terrain;
mod transmit;
mod waiters;

pub use batch::BatchBody;
pub use editors::{Editor, Editors, EditorsError, TOKEN_BYTES, editor_line, hex, new_token, token_hash, unhex};
pub use far::{NODE_REBUILD_INTERVAL, REBUILD_INTERVAL};
pub use pacing::SendBudget;
pub use payload::{GeometrySource, Payload, PayloadMode};
pub use session::{
    MAX_EDITS_IN_FLIGHT, MAX_FAR_CELLS, OUT_OF_VIEW_FACTOR, Session, SessionConfig, SessionError, SessionStats,
    cells_in,
};
pub use store::{
    CellData, CellState, CellWaker, Changes, EncodedSummary, GridStore, PlacedInstance, StoreBuilder, StoreError,
    StoreHead, SummaryCorrections, SummaryState, VersionState, WorldStore,
};
pub use summaries::{MAX_RECENT_CORRECTIONS, SummaryLru, overlaps, root_level};
pub use terrain::terrain_desc;
pub use transmit::{StreamId, Transmit};
pub use waiters::Waiters;
