//! The Canopy network client: connect to a `canopy-server` over QUIC, send the viewpoint as it moves, hold the
//! species and instance records of the area of interest, and expose them to the application and the renderer
//! (seed 001 §4: the client "allows the user to display and navigate this VE database" and needs only the data
//! items of its area of interest).
//!
//! Contract: [`state::ClientState`] is sans-IO (fed messages and viewpoints; no clock, no socket) and is what an
//! application reads: [`state::ClientState::instances`] gives every instance held with its species id, position
//! (terrain height included), seed and parameters. [`net::Connection`] drives it over QUIC. Species are cached by
//! content address in memory and on disk ([`cache::SpeciesCache`]), so a reconnecting client receives none again.
//! Everything from the network is untrusted: a bad message closes the connection with a reason.
//!
//! This crate knows no GPU, window or command line: it depends on no wgpu, winit, clap, indicatif, anyhow or
//! canopy-server (a test in `tests/tests/house.rs` holds that).

#[cfg(feature = "native")]
pub mod cache;
#[cfg(feature = "native")]
pub mod expand;
pub mod farwalk;
#[cfg(feature = "native")]
pub mod fit;
#[cfg(feature = "native")]
pub mod net;
pub mod state;
pub mod world;

#[cfg(feature = "native")]
pub use net::{ClientError, ConnectConfig, Connection, Trust};
pub use state::{ClientState, InstanceView};
