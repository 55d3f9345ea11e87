//! The Canopy world server (seed 001 §4): it stores species and instance records spatially and streams to each
//! client only its area of interest, nearest first, species once per client.
//!
//! Contract: [`session`] is sans-IO — a plain struct fed `now` and the client's messages that says what to send
//! and when; it never touches a socket or the clock, so it is tested on virtual time. [`driver`] is the small
//! quinn/tokio loop around it. [`store`] holds the world behind the [`store::WorldStore`] trait; [`cells`] expands
//! it cell by cell on demand into a bounded cache, and a session never waits for a cell. Anything a client
//! sends is untrusted: a message that does not decode, is too large or comes out of order closes that client's
//! connection with a [`canopy_protocol::CloseCode`] and a reason, and the server carries on.

pub mod admission;
pub mod batch;
pub mod cells;
pub mod driver;
pub mod editing;
pub mod editors;
pub mod far;
pub mod live;
pub mod metrics;
pub mod nats;
pub mod pacing;
pub mod payload;
pub mod session;
pub mod store;
pub mod summaries;
pub mod terrain;
pub mod tls;

pub use admission::AdmissionConfig;
pub use canopy_edits as edits;
pub use canopy_worlds as worlds;
pub use cells::{CellCache, CellCacheConfig};
pub use driver::{Server, ServerConfig, StartError};
pub use editing::EditService;
pub use editors::Editors;
pub use live::LiveStore;
pub use session::{Session, SessionConfig, SessionError, Transmit};
pub use store::{GridStore, WorldStore};
