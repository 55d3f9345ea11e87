//! canopy-editor's integration tests as one binary, a module a subject: the window's screenshot and its UI.
//! `autotests = false` in `client/editor/Cargo.toml`: a new file here is compiled only when it is named below,
//! which the house test checks.

mod screenshot;
mod ui;
