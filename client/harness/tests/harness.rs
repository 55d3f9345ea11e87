//! canopy-harness's integration tests as one binary, a module a subject: the bandwidth harness, bots' edits and
//! flight. `autotests = false` in `client/harness/Cargo.toml`: a new file here is compiled only when it is named
//! below, which the house test checks.

mod bandwidth;
mod edits;
mod flight;
