//! The cross-crate tests that run everything inside this process (servers on loopback, clients, the edit store, the
//! house rules), as one binary, a module a subject. The tests that drive programs outside it have their own binaries:
//! `browser` (Chromium), `edits_nats` (a NATS cluster), `gltf_validator` (node) and `hostile_clients` (a server
//! under hostile load). `autotests = false` in `tests/Cargo.toml`: a new file here is compiled only when a target
//! names it, which the house test checks.

mod support;

mod admission;
mod edits;
mod edits_core;
mod farfield;
mod house;
mod streaming;
mod streaming_core;
mod web;
