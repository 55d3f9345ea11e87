//! What Canopy's test binaries share, so that no fixture is typed twice: the embedded worlds loaded once per test
//! binary, a client configuration pinned to a served world (feature `net`), and Xvfb for the windowed tests.

use std::sync::{Arc, OnceLock};

use canopy_worlds::world::World;

mod xvfb;

pub use xvfb::{Reap, start_xvfb};

/// The embedded default world (`worlds/forest`), loaded once.
pub fn forest() -> &'static Arc<World> {
    static FOREST: OnceLock<Arc<World>> = OnceLock::new();
    FOREST.get_or_init(|| Arc::new(World::default_world()))
}

/// The embedded 10,486 km² `highlands`, loaded once (a function of its manifest: nothing is expanded at load).
pub fn highlands() -> &'static Arc<World> {
    static HIGHLANDS: OnceLock<Arc<World>> = OnceLock::new();
    HIGHLANDS.get_or_init(|| Arc::new(World::embedded("highlands").expect("the highlands are embedded")))
}

/// A client's configuration for `server`, its certificate pinned.
#[cfg(feature = "net")]
pub fn pinned(server: &canopy_server::Server) -> canopy_client::ConnectConfig {
    let trust = canopy_client::Trust::pinned(server.fingerprint()).expect("a server's fingerprint pins");
    canopy_client::ConnectConfig::new(server.local_addr(), trust)
}

/// The default world with every cell expanded up front ([`canopy_server::session::GridStore`]), built once and
/// shared by the servers of a test binary: a session never waits for an expansion.
#[cfg(feature = "net")]
pub fn forest_store() -> Arc<dyn canopy_server::session::WorldStore> {
    static STORE: OnceLock<Arc<dyn canopy_server::session::WorldStore>> = OnceLock::new();
    let store = STORE.get_or_init(|| {
        canopy_server::session::GridStore::from_world(forest()).expect("the default world builds a store").shared()
    });
    Arc::clone(store)
}
