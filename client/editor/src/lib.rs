//! Canopy's species editor (`canopy species edit`, seed 001 §6: "an interactive graphical editor … that allows
//! convenient specification of RECURSIV models with interactive previewing and tweaking of parameters").
//!
//! Contract: the editor model ([`model::Editor`]) is pure — source text, diagnostics at `file:line:col`, the last
//! good model (a broken edit never replaces it), the previewed instance and its stream — and is tested without a
//! window. The UI ([`ui::EditorUi`]) is egui drawing that model; the preview ([`preview::Preview`]) draws the model
//! with the renderer crate into a texture the UI shows; [`window`] is the winit/wgpu loop and [`screenshot`] the same
//! frame rendered offscreen once. Files are read through `canopy_worlds::fsread` and watched with `notify`. The
//! editor knows no network.

pub mod grid;
mod hyp;
pub mod last_good;
mod model;
pub mod preview;
pub mod save;
pub mod screenshot;
pub mod species;
pub mod stats;
pub mod ui;
mod ui_source;
mod watch;
mod window;

use std::path::PathBuf;

pub use model::Editor;
pub use ui::EditorUi;

/// What `canopy species edit` was asked to do, validated once by the CLI.
#[derive(Clone, Debug, PartialEq)]
pub struct EditConfig {
    /// The file (or embedded library species name); `None` starts a new species.
    pub file: Option<PathBuf>,
    /// Parameter overrides, `name=value`.
    pub params: Vec<(String, f32)>,
    /// The previewed seed.
    pub seed: u64,
    /// The detail level.
    pub detail: u8,
    /// Render the window once into this PNG and exit.
    pub screenshot: Option<PathBuf>,
    /// Window (or screenshot) size, pixels.
    pub size: (u32, u32),
    /// The view to start in.
    pub view: ui::View,
    /// Close the window by itself after this long (tests, demos); `None` runs until it is closed.
    pub exit_after: Option<std::time::Duration>,
    /// Where the last good version of each opened file is kept ([`last_good`]); `None` keeps none.
    pub last_good: Option<last_good::LastGood>,
}

impl Default for EditConfig {
    fn default() -> Self {
        EditConfig {
            file: None,
            params: Vec::new(),
            seed: 1,
            detail: 0,
            screenshot: None,
            size: (1280, 800),
            view: ui::View::Tree,
            exit_after: None,
            last_good: None,
        }
    }
}

/// Why the editor could not do something.
#[derive(Debug, thiserror::Error)]
pub enum EditorError {
    /// The file name names no known format.
    #[error("{0}: unknown format: expected a `.species`, `.lsys` or `.hyp` file")]
    Format(String),
    /// The file could not be read.
    #[error("{path}: {reason}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
    /// The file could not be written.
    #[error("writing {path}: {reason}")]
    Write {
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
    /// The path to write exists and is not a regular file (a directory, a symbolic link, a device…).
    #[error("{path}: {kind}: refusing to write over it (the editor writes regular files only)")]
    NotAFile {
        /// The path.
        path: String,
        /// What it is.
        kind: &'static str,
    },
    /// The buffer has no file to save to.
    #[error("the buffer has no file: start the editor with a path to save")]
    NoPath,
    /// Nothing has parsed yet.
    #[error("no species has parsed yet")]
    NoModel,
    /// A parameter setting was refused.
    #[error("{0}")]
    Param(String),
    /// The glTF export failed.
    #[error("export: {0}")]
    Export(String),
    /// No GPU, or rendering failed.
    #[error(transparent)]
    Gpu(#[from] canopy_render::GpuError),
    /// The offscreen frame could not be rendered or written.
    #[error("screenshot: {0}")]
    Screenshot(String),
    /// The window could not be opened or run.
    #[error("window: {0}")]
    Window(String),
    /// The renderer could not be set up.
    #[error("renderer: {0}")]
    Renderer(String),
}

/// Run `canopy species edit`: the window, or one screenshot when asked for.
pub fn run(cfg: &EditConfig) -> Result<(), EditorError> {
    let mut ui = EditorUi::open(cfg)?;
    match &cfg.screenshot {
        Some(out) => {
            let img = screenshot::render(&mut ui, cfg.size)?;
            img.save_png(out).map_err(|e| EditorError::Screenshot(e.to_string()))
        }
        None => window::run(ui, cfg.size, cfg.exit_after),
    }
}
