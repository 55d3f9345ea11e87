//! canopy-protocol's integration tests as one binary, a module a subject (`autotests = false` in
//! `protocol/Cargo.toml`: a new file here is compiled only when it is named below, which the house test checks).

mod wire;

mod edit;
mod messages;
mod species_codec;
mod summary;
