//! Canopy's harness: headless bots that walk scripted paths over a real QUIC connection and are verified against
//! the world itself ([`bots`]), and the bandwidth harness that measures procedural streaming against explicit
//! geometry over emulated links ([`bandwidth`]). It may run a `canopy-server` in process; it draws nothing and
//! parses no command line (no wgpu, winit or canopy-render: `tests/tests/house.rs`).

pub mod bandwidth;
pub mod bots;
pub mod hole;
pub mod numbers;
