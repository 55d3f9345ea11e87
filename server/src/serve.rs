//! One way to serve a world: [`serve`] builds the world store a server reads (materialised, or expanded cell by cell
//! on demand), lays the durable edits over it ([`LiveStore`], [`EditService`]) and starts the QUIC [`Server`]. The
//! `canopy-server` binary, `canopy walk` and `canopy demo` with a server in process, the bandwidth harness and the
//! tests all start servers through it, so the wiring is written once.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use canopy_edits::{EditStore, EditStoreError, MemoryEditStore, SqliteEditStore};
use canopy_session::{GridStore, StoreError, WorldStore};
use canopy_worlds::world::{EAGER_CELLS, World};

use crate::cells::{CellCache, CellCacheConfig};
use crate::driver::{Server, ServerConfig, StartError};
use crate::editing::EditService;
use crate::live::LiveStore;
use crate::metrics::EngineMetrics;
use crate::nats::{NatsConfig, NatsEditStore};

/// How the world function's cells are held.
#[derive(Clone, Debug)]
pub enum Cells {
    /// Materialised at start when the world has at most [`EAGER_CELLS`] cells, else on demand with this cache.
    Auto(CellCacheConfig),
    /// Every cell expanded at start ([`GridStore`]): small worlds, exact tests.
    Materialised,
    /// Expanded by worker threads when first asked for, kept in a byte-bounded cache ([`CellCache`]).
    OnDemand(CellCacheConfig),
}

impl Default for Cells {
    fn default() -> Self {
        Cells::Auto(CellCacheConfig::default())
    }
}

/// Where the edits are kept.
#[derive(Clone, Default)]
pub enum Edits {
    /// None: the world is the function of its manifest; every edit is denied.
    #[default]
    ReadOnly,
    /// In memory, for this process's life.
    Memory,
    /// `edits.sqlite` in this directory (created if missing): the embedded durable store.
    Sqlite(PathBuf),
    /// A NATS JetStream stream shared by every edge of the world.
    Nats(NatsConfig),
    /// A store the caller built (and may read itself, as tests do).
    Store(Arc<dyn EditStore>),
}

impl std::fmt::Debug for Edits {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Edits::ReadOnly => f.write_str("ReadOnly"),
            Edits::Memory => f.write_str("Memory"),
            Edits::Sqlite(dir) => f.debug_tuple("Sqlite").field(dir).finish(),
            Edits::Nats(cfg) => f.debug_tuple("Nats").field(cfg).finish(),
            Edits::Store(_) => f.write_str("Store(..)"),
        }
    }
}

/// How to serve a world: the server's own options, how cells are held, where edits are kept.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    /// Address, certificate, sessions, admission (its `edits` is set by [`serve`] from [`ServeOptions::edits`]).
    pub server: ServerConfig,
    /// How the world function's cells are held.
    pub cells: Cells,
    /// Where the edits are kept.
    pub edits: Edits,
    /// Memory for cells' edit overlays (and edited cells' records), bytes.
    pub overlay_cache_bytes: usize,
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            server: ServerConfig::default(),
            cells: Cells::default(),
            edits: Edits::ReadOnly,
            overlay_cache_bytes: 64 << 20,
        }
    }
}

/// Why a world could not be served.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The world's store could not be built.
    #[error("building the world store: {0}")]
    Store(#[from] StoreError),
    /// The edit store could not be opened or read.
    #[error("the edit store ({at}): {source}")]
    Edits {
        /// Where it is.
        at: String,
        /// What failed.
        source: EditStoreError,
    },
    /// The server could not start.
    #[error(transparent)]
    Start(#[from] StartError),
}

/// A world being served: the running server, the edit pipeline, and what was set up (for a start-up banner).
pub struct Served {
    server: Server,
    store: Arc<dyn WorldStore>,
    live: Option<Arc<LiveStore>>,
    edits: Option<Arc<EditService>>,
    cells: String,
    edits_at: String,
    edit_count: u64,
}

impl std::fmt::Debug for Served {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Served").field("server", &self.server).field("cells", &self.cells).finish()
    }
}

/// Serve `world` as `opts` say (in the current tokio runtime).
pub async fn serve(world: World, opts: ServeOptions) -> Result<Served, ServeError> {
    let materialise = match &opts.cells {
        Cells::Materialised => true,
        Cells::OnDemand(_) => false,
        Cells::Auto(_) => world.cell_count() <= EAGER_CELLS as u64,
    };
    let (store, cells) = match opts.cells {
        Cells::OnDemand(cfg) | Cells::Auto(cfg) if !materialise => {
            let how = format!(
                "cells expanded on demand by {} workers, cached up to {} MiB",
                cfg.workers,
                cfg.limit_bytes >> 20
            );
            // The cache expands the world's cells on demand (`World::expand_cell`) and keeps the manifest to do so.
            (CellCache::new(world, cfg)?.shared(), how)
        }
        _ => (GridStore::from_world(&world)?.shared(), "cells expanded at start".to_owned()),
    };
    start(store, cells, opts).await
}

/// Serve a store built beforehand (tests share one between servers); [`ServeOptions::cells`] is not read.
pub async fn serve_store(store: Arc<dyn WorldStore>, opts: ServeOptions) -> Result<Served, ServeError> {
    start(store, "cells held by the caller's store".to_owned(), opts).await
}

async fn start(store: Arc<dyn WorldStore>, cells: String, opts: ServeOptions) -> Result<Served, ServeError> {
    let (edit_store, edits_at, engine): (Option<Arc<dyn EditStore>>, String, Option<Arc<EngineMetrics>>) =
        match opts.edits {
            Edits::ReadOnly => (None, "nowhere (read-only)".into(), None),
            Edits::Memory => (Some(Arc::new(MemoryEditStore::new())), "memory".into(), None),
            Edits::Sqlite(dir) => {
                let at = dir.join(canopy_edits::sqlite::FILE_NAME).display().to_string();
                let s = SqliteEditStore::open(&dir).map_err(|source| ServeError::Edits { at: at.clone(), source })?;
                (Some(Arc::new(s)), at, None)
            }
            Edits::Nats(cfg) => {
                let at = format!("NATS JetStream stream {} ({} replicas)", cfg.stream(), cfg.replicas);
                let s = NatsEditStore::connect(cfg).map_err(|source| ServeError::Edits { at: at.clone(), source })?;
                let engine = Arc::clone(s.metrics());
                (Some(Arc::new(s)), at, Some(engine))
            }
            Edits::Store(s) => (Some(s), "the caller's store".into(), None),
        };
    let mut cfg = opts.server;
    let (served_store, live, edits, edit_count) = match edit_store {
        Some(edit_store) => {
            let edit_count = edit_store.count().map_err(|source| ServeError::Edits { at: edits_at.clone(), source })?;
            let live = Arc::new(LiveStore::new(Arc::clone(&store), edit_store, opts.overlay_cache_bytes));
            let edits = EditService::start(Arc::clone(&live));
            (Arc::clone(&live) as Arc<dyn WorldStore>, Some(live), Some(edits), edit_count)
        }
        None => (store, None, None, 0),
    };
    // The pipeline is the one made here (`None`: read-only), whatever the options said.
    cfg.edits = edits.clone();
    let server = match Server::start(Arc::clone(&served_store), cfg).await {
        Ok(server) => server,
        Err(e) => {
            if let Some(edits) = &edits {
                edits.stop();
            }
            return Err(e.into());
        }
    };
    if let Some(engine) = engine {
        server.metrics().attach_engine(engine);
    }
    Ok(Served { server, store: served_store, live, edits, cells, edits_at, edit_count })
}

impl Served {
    /// The running server (address, fingerprint, metrics).
    pub fn server(&self) -> &Server {
        &self.server
    }

    /// The store the sessions read (the live world where edits are taken).
    pub fn store(&self) -> &Arc<dyn WorldStore> {
        &self.store
    }

    /// The live world (`None`: read-only).
    pub fn live(&self) -> Option<&Arc<LiveStore>> {
        self.live.as_ref()
    }

    /// The edit pipeline (`None`: read-only).
    pub fn edits(&self) -> Option<&Arc<EditService>> {
        self.edits.as_ref()
    }

    /// How the world's cells are held, in words.
    pub fn cells(&self) -> &str {
        &self.cells
    }

    /// Where the edits are kept, in words.
    pub fn edits_at(&self) -> &str {
        &self.edits_at
    }

    /// Edits stored when the server started.
    pub fn edit_count(&self) -> u64 {
        self.edit_count
    }

    /// Close every connection (waiting up to `grace`), then stop the edit pipeline.
    pub async fn shutdown(self, grace: Duration) {
        self.server.shutdown(grace).await;
        if let Some(edits) = self.edits {
            edits.stop();
        }
    }
}

impl std::ops::Deref for Served {
    type Target = Server;

    fn deref(&self) -> &Server {
        &self.server
    }
}
