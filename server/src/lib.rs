//! The Canopy world server (seed 001 §4): it stores species and instance records spatially and streams to each
//! client only its area of interest, nearest first, species once per client.
//!
//! This crate is the I/O around the sans-IO core of [`canopy_session`]: [`serve`] builds a world's store (cells
//! materialised, or expanded on demand by worker threads into a bounded cache, [`CellCache`]), lays the durable
//! edits over it ([`LiveStore`], written by the [`EditService`] to SQLite or NATS JetStream) and runs the quinn/tokio
//! [`Server`] that drives one [`canopy_session::Session`] per client. Anything a client sends is untrusted: a
//! message that does not decode, is too large or comes out of order closes that client's connection with a
//! [`canopy_protocol::CloseCode`] and a reason, and the server carries on.

mod admission;
mod bake;
mod cells;
mod driver;
mod editing;
mod http;
mod live;
mod metrics;
mod nats;
mod outbox;
mod serve;
mod tls;

pub use admission::{AdmissionConfig, Refusal};
pub use bake::{BakeError, Baked, bake};
pub use canopy_edits as edits;
pub use canopy_session as session;
pub use canopy_worlds as worlds;
pub use cells::{CellCache, CellCacheConfig};
pub use driver::{MAX_ENDPOINTS, OWED_SLACK, SEND_WINDOW, Server, ServerConfig, StartError, WEB_PATH, WebConfig};
pub use editing::{EditJob, EditMetrics, EditService, Reply};
pub use http::{MAX_PAGE_FILE, WebPage};
pub use live::{CellChange, EditHub, LiveStore};
pub use metrics::{EngineMetrics, Metrics, resident_bytes};
pub use nats::{NatsConfig, NatsEditStore};
pub use serve::{Cells, Edits, ServeError, ServeOptions, Served, serve, serve_store};
pub use tls::{Identity, IdentityError, WEB_CERT_ROTATION, WEB_CERT_VALIDITY, WebCertificate};
