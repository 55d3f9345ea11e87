//! canopy-server's integration tests as one binary, a module a subject: the cell store and the far view.
//! `autotests = false` in `server/Cargo.toml`: a new file here is compiled only when it is named below, which the
//! house test checks.

mod cells;
mod far;
